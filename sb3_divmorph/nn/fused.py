"""Actor and critic in one pass: the rollout step of a MetaMorph policy as one stacked computation.

A MetaMorph policy runs two Transformers of the same shape (actor and critic) one after the other. A
rollout step feeds them a handful of samples, so each op costs mostly its fixed overhead, and two towers
pay it twice. :class:`FusedTowers` runs both as one: the towers' weights stacked along a leading axis of
2 (``bmm``), the shared input's projections as one matmul over the two weights side by side, one
attention call over ``2B`` sequences. The stacked weights are built once per parameter version -- once per
rollout, since the update changes them -- so the rollout's hundreds of steps pay the stacking once.

The math is the separate pass's: the latents equal it up to float rounding (``tests/test_policies.py``).
Training passes (autograd on) never take this path: there the stacking would be paid at every minibatch and
the towers' parameters stay separate tensors, which per-tower learning rates and freezing need.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, cast

import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_divmorph.nn.decoders import TokenMLP
from sb3_divmorph.nn.extractors import CONTEXT, PROPRIOCEPTIVE, MorphologyTransformerExtractor, token_padding
from sb3_divmorph.nn.layers import DenseLinear, FactorizedLinear
from sb3_divmorph.nn.transformer import TransformerEncoderLayer, attention_mask


def _dense_only(*modules: nn.Module) -> bool:
    """Every projection inside is a dense layer (no factorized, gated or adapted unit)."""
    for module in modules:
        for sub in module.modules():
            if isinstance(sub, nn.Linear) and type(sub) not in (DenseLinear, nn.Linear):
                return False
            if isinstance(sub, FactorizedLinear):
                return False
    return True


def _stack(*tensors: th.Tensor) -> th.Tensor:
    return th.stack([t.detach() for t in tensors])


class FusedTowers:
    """The actor's and the critic's per-token latents of a two-tower dense policy, computed as one.

    It holds the parameters the towers had when it was made and restacks them whenever one changes in place (an
    optimiser step, ``load_state_dict``). A part replaced by a new module makes the policy build a new one; a
    parameter replaced by a new tensor inside a part is not seen (a walk over the modules at every step would
    cost ~180 us, more than a tenth of the pass).

    :param actor: the actor's extractor.
    :param critic: the critic's extractor (same sizes as the actor's).
    :param actor_decoder: the actor's per-token MLP (``mlp_extractor.policy_net``).
    :param critic_decoder: the critic's per-token MLP (``mlp_extractor.value_net``).
    """

    def __init__(
        self,
        actor: MorphologyTransformerExtractor,
        critic: MorphologyTransformerExtractor,
        actor_decoder: TokenMLP,
        critic_decoder: TokenMLP,
    ):
        self.towers = (actor, critic)
        self.decoders = (actor_decoder, critic_decoder)
        self.parameters = [p for module in (*self.towers, *self.decoders) for p in module.parameters()]
        self._key: tuple | None = None
        self._weights: dict[str, Any] = {}

    @classmethod
    def of(cls, policy: Any) -> FusedTowers | None:
        """The fused pass of ``policy`` when its towers allow one (two dense MetaMorph towers of the same sizes,
        with the same decoder widths), else ``None``."""
        if policy.share_features_extractor or policy.mixed_precision:
            return None
        actor, critic = policy.pi_features_extractor, policy.vf_features_extractor
        decoders = (policy.mlp_extractor.policy_net, policy.mlp_extractor.value_net)
        if not all(type(t) is MorphologyTransformerExtractor for t in (actor, critic)):
            return None
        if not _dense_only(actor, critic, *decoders):
            return None
        same = (
            actor.use_context == critic.use_context
            and list(actor.exteroception) == list(critic.exteroception)
            and [p.shape for p in actor.parameters()] == [p.shape for p in critic.parameters()]
            and [p.shape for p in decoders[0].parameters()] == [p.shape for p in decoders[1].parameters()]
            and [type(a) for a in decoders[0].activations] == [type(a) for a in decoders[1].activations]
        )
        return cls(actor, critic, *decoders) if same else None

    # -- the stacked weights, once per parameter version ----------------------------------------------
    def _stacked(self) -> dict[str, Any]:
        key = tuple((p.data_ptr(), p._version) for p in self.parameters)
        if key == self._key:
            return self._weights
        actor, critic = self.towers
        w: dict[str, Any] = {
            # the shared input meets both towers' embeddings in one matmul: their weights side by side
            "embed_w": th.cat([actor.embedding.linear.weight, critic.embedding.linear.weight]).detach(),
            "embed_b": th.cat([actor.embedding.linear.bias, critic.embedding.linear.bias]).detach(),
            "position": _stack(actor.embedding.position, critic.embedding.position).transpose(0, 1),  # (L, 2, d)
            "layers": [],
            "extero": {},
            "decoder": [],
        }
        for a, c in zip(actor.encoder.layers, critic.encoder.layers):
            a, c = cast(Any, a), cast(Any, c)  # their projections come from a builder: typed as modules
            qkv = [th.cat([m.attention.q.weight, m.attention.k.weight, m.attention.v.weight]) for m in (a, c)]
            qkv_b = [th.cat([m.attention.q.bias, m.attention.k.bias, m.attention.v.bias]) for m in (a, c)]
            w["layers"].append(
                {
                    "norm1": (_stack(a.norm1.weight, c.norm1.weight)[:, None], _stack(a.norm1.bias, c.norm1.bias)[:, None]),
                    "norm2": (_stack(a.norm2.weight, c.norm2.weight)[:, None], _stack(a.norm2.bias, c.norm2.bias)[:, None]),
                    "qkv": (_stack(*qkv).transpose(1, 2), _stack(*qkv_b)[:, None]),
                    "o": (
                        _stack(a.attention.o.weight, c.attention.o.weight).transpose(1, 2),
                        _stack(a.attention.o.bias, c.attention.o.bias)[:, None],
                    ),
                    "ff_in": (_stack(a.ff_in.weight, c.ff_in.weight).transpose(1, 2), _stack(a.ff_in.bias, c.ff_in.bias)[:, None]),
                    "ff_out": (_stack(a.ff_out.weight, c.ff_out.weight).transpose(1, 2), _stack(a.ff_out.bias, c.ff_out.bias)[:, None]),
                }
            )
        for key_name in actor.exteroception:
            layers_a: list[Any] = [m for m in cast(Any, actor.exteroception[key_name]) if isinstance(m, nn.Linear)]
            layers_c: list[Any] = [m for m in cast(Any, critic.exteroception[key_name]) if isinstance(m, nn.Linear)]
            first = (th.cat([layers_a[0].weight, layers_c[0].weight]).detach(), th.cat([layers_a[0].bias, layers_c[0].bias]).detach())
            rest = [
                (_stack(la.weight, lc.weight).transpose(1, 2), _stack(la.bias, lc.bias)[:, None])
                for la, lc in zip(layers_a[1:], layers_c[1:])
            ]
            w["extero"][key_name] = (first, rest)
        for la, lc in zip(cast(Any, self.decoders[0].layers), cast(Any, self.decoders[1].layers)):
            w["decoder"].append((_stack(la.weight, lc.weight).transpose(1, 2), _stack(la.bias, lc.bias)[:, None]))
        self._key, self._weights = key, w
        return w

    # -- the pass ---------------------------------------------------------------------------------------
    def latents(self, observations: Mapping[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """``(actor latent, critic latent)``, each (B, L, decoder width): what the separate towers and
        decoders give for ``observations`` (preprocessed), up to float rounding."""
        w = self._stacked()
        actor = self.towers[0]
        padding = token_padding(observations)
        tokens = observations[PROPRIOCEPTIVE]
        if actor.use_context:
            tokens = th.cat([tokens, observations[CONTEXT]], dim=-1)
        tokens = th.where(padding[..., None], th.zeros((), dtype=tokens.dtype, device=tokens.device), tokens)
        batch, length, _ = tokens.shape
        d = actor.d_model
        x = F.linear(tokens, w["embed_w"], w["embed_b"]).view(batch, length, 2, d) * actor.embedding.scale + w["position"]
        x = x.permute(2, 0, 1, 3).reshape(2, batch * length, d)  # (tower, B*L, d)
        mask = attention_mask(padding).repeat(2, 1, 1, 1)  # the 2B sequences: actor's then critic's
        for layer, lw in zip(actor.encoder.layers, w["layers"]):
            layer = cast(TransformerEncoderLayer, layer)
            heads, head_dim = layer.attention.n_heads, layer.attention.head_dim
            h = F.layer_norm(x, (d,), eps=layer.norm1.eps) * lw["norm1"][0] + lw["norm1"][1]
            qkv = th.baddbmm(lw["qkv"][1], h, lw["qkv"][0]).view(2 * batch, length, 3, heads, head_dim)
            q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)
            attended = F.scaled_dot_product_attention(q, k, v, attn_mask=mask).transpose(1, 2).reshape(2, batch * length, d)
            x = x + th.baddbmm(lw["o"][1], attended, lw["o"][0])
            h = F.layer_norm(x, (d,), eps=layer.norm2.eps) * lw["norm2"][0] + lw["norm2"][1]
            x = x + th.baddbmm(lw["ff_out"][1], layer.activation(th.baddbmm(lw["ff_in"][1], h, lw["ff_in"][0])), lw["ff_out"][0])
        features = x.view(2, batch, length, d)
        if len(actor.exteroception):
            encodings = []
            for key_name, ((first_w, first_b), rest) in w["extero"].items():
                e = F.relu(F.linear(observations[key_name].flatten(1), first_w, first_b))  # (B, 2 * width)
                e = e.view(batch, 2, -1).transpose(0, 1)
                for weight, bias in rest:
                    e = F.relu(th.baddbmm(bias, e, weight))
                encodings.append(e)
            extero = th.cat(encodings, dim=-1)  # (2, B, E)
            features = th.cat([features, extero[:, :, None, :].expand(-1, -1, length, -1)], dim=-1)
        latent = features.reshape(2, batch * length, -1)
        for (weight, bias), activation in zip(w["decoder"], self.decoders[0].activations):
            latent = activation(th.baddbmm(bias, latent, weight))
        latent = latent.view(2, batch, length, -1)
        return latent[0], latent[1]
