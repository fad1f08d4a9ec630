"""Actor and critic in one pass: the rollout step of a two-tower policy as one stacked computation.

A MetaMorph or DivMorph policy runs two Transformers of the same shape (actor and critic) one after the
other. A rollout step feeds them a handful of samples, so each op costs mostly its fixed overhead, and two
towers pay it twice. :class:`FusedTowers` runs both as one: the towers' weights stacked along a leading axis
(``bmm``), the shared input's embeddings as one matmul over the two weights side by side, one attention call
over ``2B`` sequences.

A DivMorph actor's projections are factorized and gated per sample (``W_b = U diag(s g_b) V^T``). In a rollout
the gates change only when an environment draws a new robot, so each sample's weight is built whole once and
the actor's projection becomes one batched matmul over the ``B`` samples, stacked with the critic's dense weight
repeated ``B`` times: the two towers again run as one ``bmm`` over ``2B`` weights. Stacked weights are built once
per parameter version (once per rollout, since the update changes them) and per gate batch.

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
from sb3_divmorph.nn.extractors import CONTEXT, OBS_PADDING_MASK, PROPRIOCEPTIVE, MorphologyTransformerExtractor, token_padding
from sb3_divmorph.nn.layers import DenseLinear, FactorizedLinear
from sb3_divmorph.nn.transformer import TransformerEncoderLayer, attention_mask


def _projections(module: nn.Module) -> list[Any]:
    return [m for m in module.modules() if isinstance(m, (nn.Linear, FactorizedLinear))]


def _dense_only(*modules: nn.Module) -> bool:
    """Every projection inside is a dense layer (no factorized, gated or adapted unit)."""
    return all(type(m) in (DenseLinear, nn.Linear) for module in modules for m in _projections(module))


def _signature(module: nn.Module) -> list[tuple]:
    """What must match between the towers for one stacked pass: each projection's sizes and bias, each
    norm's and the position embedding's shape, in the order the modules sit."""
    signature: list[tuple] = []
    for m in cast(Any, module).modules():  # typed loosely: each kind's attributes are read below
        if isinstance(m, (nn.Linear, FactorizedLinear)):
            signature.append(("linear", m.in_features, m.out_features, m.bias is not None))
        elif isinstance(m, nn.LayerNorm):
            signature.append(("norm", tuple(m.normalized_shape), m.eps))
        elif hasattr(m, "position"):
            signature.append(("position", tuple(m.position.shape)))
        elif not isinstance(m, (nn.ReLU, nn.GELU, nn.Identity, nn.Dropout, nn.Tanh)) and any(True for _ in m.parameters(recurse=False)):
            signature.append(("other", type(m).__name__))  # a part the stacked pass does not know: no fusing
    return signature


def _same(a: th.Tensor | None, b: th.Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and a.device == b.device and th.equal(a, b)


def _stack(*tensors: th.Tensor) -> th.Tensor:
    return th.stack([t.detach() for t in tensors])


def _weight(layer: Any, gates: th.Tensor | None) -> tuple[th.Tensor, th.Tensor]:
    """``(weight, bias)`` of one projection, the weight transposed for ``x @ weight``: (in, out) when every sample
    shares it, (B, in, out) when the layer is gated (each sample's own ``U diag(s g_b) V^T``)."""
    weight: th.Tensor
    if not isinstance(layer, FactorizedLinear):
        weight = layer.weight.detach().T
    elif gates is None or layer.n_tailors == 0:
        weight = layer.dense_weight(None).detach().T
    else:
        U, V = layer.factors()[:2]
        weight = th.einsum("ir,br,or->bio", V, layer.unit_scales(gates), U)  # (B, in, out)
        if layer.adapter_rank:
            weight = weight + (layer.adapter_up @ layer.adapter_down).T
    bias: th.Tensor = layer.bias if layer.bias is not None else weight.new_zeros(layer.out_features)
    return weight.detach(), bias.detach()


def _pair(actor: tuple[th.Tensor, th.Tensor], critic: tuple[th.Tensor, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
    """The two towers' ``(weight, bias)`` stacked: (2, in, out) and (2, 1, out) when both are shared, else the actor's
    B per-sample weights then the critic's repeated B times, (2B, in, out) and (2B, 1, out)."""
    (wa, ba), (wc, bc) = actor, critic
    if wa.dim() == 2:
        return th.stack([wa, wc]), th.stack([ba, bc])[:, None]
    batch = wa.shape[0]
    return th.cat([wa, wc.expand(batch, -1, -1)]), th.cat([ba.expand(batch, -1), bc.expand(batch, -1)])[:, None]


def _project(x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
    """(2, N, in) rows of both towers (N = B * rows per sample) -> (2, N, out) through :func:`_pair`'s weights."""
    if weight.shape[0] == 2:
        return th.baddbmm(bias, x, weight)
    per_sample = x.reshape(weight.shape[0], -1, x.shape[-1])  # (2B, rows per sample, in): the same memory
    return th.baddbmm(bias, per_sample, weight).view(2, x.shape[1], -1)


class FusedTowers:
    """The actor's and the critic's per-token latents of a two-tower policy, computed as one.

    The critic is dense; the actor is dense (MetaMorph) or factorized and gated (DivMorph). It holds the parameters
    the towers had when it was made and restacks them whenever one changes in place (an optimiser step,
    ``load_state_dict``, a rebase of the square factors) or the gates change (an environment drew a new robot).
    A part replaced by a new module makes the policy build a new one; a parameter replaced by a new tensor inside
    a part is not seen (a walk over the modules at every step would cost ~180 us, more than a tenth of the pass).

    :param actor: the actor's extractor.
    :param critic: the critic's extractor (same sizes as the actor's; dense).
    :param actor_decoder: the actor's per-token MLP (``mlp_extractor.policy_net``).
    :param critic_decoder: the critic's per-token MLP (``mlp_extractor.value_net``; dense).
    """

    #: the most samples whose gated actor runs as per-sample weights (B x the layers' in x out floats; a GPU
    #: rollout of thousands of worlds would hold gigabytes): larger gated batches run the towers one after the other
    max_per_sample_batch: int = 256

    def __init__(
        self,
        actor: MorphologyTransformerExtractor,
        critic: MorphologyTransformerExtractor,
        actor_decoder: TokenMLP,
        critic_decoder: TokenMLP,
    ):
        self.towers = (actor, critic)
        self.decoders = (actor_decoder, critic_decoder)
        modules = (*self.towers, *self.decoders)
        self.tensors = [t for module in modules for t in (*module.parameters(), *module.buffers())]
        self._key: tuple | None = None
        self._gates: th.Tensor | None = None
        self._weights: dict[str, Any] = {}
        self._robots: dict[str, Any] | None = None

    @classmethod
    def of(cls, policy: Any) -> FusedTowers | None:
        """The fused pass of ``policy`` when its towers allow one (two MetaMorph-shaped towers of the same sizes, a
        dense critic, the same decoder widths and activations), else ``None``."""
        if policy.share_features_extractor or policy.mixed_precision:
            return None
        actor, critic = policy.pi_features_extractor, policy.vf_features_extractor
        decoders = (policy.mlp_extractor.policy_net, policy.mlp_extractor.value_net)
        if not all(type(t) is MorphologyTransformerExtractor for t in (actor, critic)):
            return None
        if not all(type(d) is TokenMLP for d in decoders) or not _dense_only(critic, decoders[1]):
            return None
        same = (
            actor.use_context == critic.use_context
            and list(actor.exteroception) == list(critic.exteroception)
            and _signature(actor) == _signature(critic)
            and _signature(decoders[0]) == _signature(decoders[1])
            and [type(a) for a in decoders[0].activations] == [type(a) for a in decoders[1].activations]
            and all(("other",) != entry[:1] for entry in _signature(actor) + _signature(decoders[0]))
        )
        return cls(actor, critic, *decoders) if same else None

    def takes(self, tailor_gates: th.Tensor | None) -> bool:
        """Whether this pass runs a batch with these gates (a gated batch only up to :attr:`max_per_sample_batch`)."""
        return tailor_gates is None or tailor_gates.shape[0] <= self.max_per_sample_batch

    # -- the stacked weights, once per parameter version and gate batch ---------------------------------
    def _stacked(self, gates: th.Tensor | None) -> dict[str, Any]:
        key = tuple((t.data_ptr(), t._version) for t in self.tensors)
        same_gates = gates is self._gates or (
            gates is not None and self._gates is not None and gates.shape == self._gates.shape and th.equal(gates, self._gates)
        )
        if key == self._key and same_gates:
            return self._weights
        actor, critic = self.towers
        # the shared input meets both towers' embeddings in one matmul: their weights side by side, the proprioceptive
        # columns (read every step, the embedding's scale folded in) apart from the context's (read once per robot)
        embed_w = th.cat([actor.embedding.linear.weight, critic.embedding.linear.weight]).detach()
        n_proprio = self._n_proprio
        w: dict[str, Any] = {
            "embed_proprio": embed_w[:, :n_proprio] * actor.embedding.scale,
            "embed_context": embed_w[:, n_proprio:],
            "embed_b": th.cat([actor.embedding.linear.bias, critic.embedding.linear.bias]).detach(),
            "position": _stack(actor.embedding.position, critic.embedding.position).transpose(0, 1),  # (L, 2, d)
            "layers": [],
            "extero": {},
            "decoder": [],
        }
        for a, c in zip(actor.encoder.layers, critic.encoder.layers):
            a, c = cast(Any, a), cast(Any, c)  # their projections come from a builder: typed as modules
            qkv = [[_weight(getattr(m.attention, name), g) for name in "qkv"] for m, g in ((a, gates), (c, None))]
            qkv_pair = [(th.cat([w for w, _ in parts], dim=-1), th.cat([b for _, b in parts])) for parts in qkv]
            w["layers"].append(
                {
                    "norm1": (_stack(a.norm1.weight, c.norm1.weight)[:, None], _stack(a.norm1.bias, c.norm1.bias)[:, None]),
                    "norm2": (_stack(a.norm2.weight, c.norm2.weight)[:, None], _stack(a.norm2.bias, c.norm2.bias)[:, None]),
                    "qkv": _pair(*qkv_pair),
                    "o": _pair(_weight(a.attention.o, gates), _weight(c.attention.o, None)),
                    "ff_in": _pair(_weight(a.ff_in, gates), _weight(c.ff_in, None)),
                    "ff_out": _pair(_weight(a.ff_out, gates), _weight(c.ff_out, None)),
                }
            )
        for key_name in actor.exteroception:
            layers_a = _projections(actor.exteroception[key_name])
            layers_c = _projections(critic.exteroception[key_name])
            if not _dense_only(actor.exteroception[key_name]):
                w["extero"][key_name] = None  # a diverted encoder: each tower runs its own (see ``latents``)
                continue
            first = (th.cat([layers_a[0].weight, layers_c[0].weight]).detach(), th.cat([layers_a[0].bias, layers_c[0].bias]).detach())
            rest = [_pair(_weight(la, None), _weight(lc, None)) for la, lc in zip(layers_a[1:], layers_c[1:])]
            w["extero"][key_name] = (first, rest)
        for la, lc in zip(self.decoders[0].layers, self.decoders[1].layers):
            w["decoder"].append(_pair(_weight(la, gates), _weight(lc, None)))
        self._key, self._gates, self._weights = key, gates, w
        return w

    @property
    def _n_proprio(self) -> int:
        """Features of a token's proprioceptive part: the embedding's first input columns (the context's follow)."""
        return int(cast(Any, self.towers[0])._observation_space[PROPRIOCEPTIVE].shape[-1])

    def _robot_constants(self, observations: Mapping[str, th.Tensor], w: dict[str, Any]) -> dict[str, Any]:
        """What the step's robots fix, kept while they (padding mask and context) and the weights stay the same:
        the padded slots, the attention mask of the 2B sequences, and the embedding's constant part (the context's
        columns, the bias, the scale and the position embedding)."""
        padding_in = observations[OBS_PADDING_MASK]
        context = observations[CONTEXT] if self.towers[0].use_context else None
        cached = self._robots
        if cached is not None and cached["weights"] is w and _same(padding_in, cached["padding_in"]) and _same(context, cached["context"]):
            return cached
        padding = token_padding(observations)
        batch, length = padding.shape
        constant = w["embed_b"].expand(batch, length, -1)
        if context is not None:
            zeroed = th.where(padding[..., None], th.zeros((), dtype=context.dtype, device=context.device), context)
            constant = F.linear(zeroed, w["embed_context"], w["embed_b"])
        embedding = constant.view(batch, length, 2, -1) * self.towers[0].embedding.scale + w["position"]
        self._robots = {
            "weights": w,
            "padding_in": padding_in.clone(),
            "context": None if context is None else context.clone(),
            "padding": padding[..., None],
            "mask": attention_mask(padding).repeat(2, 1, 1, 1),  # the 2B sequences: actor's then critic's
            "embedding": embedding,  # (B, L, 2, d)
        }
        return self._robots

    # -- the pass ---------------------------------------------------------------------------------------
    def latents(self, observations: Mapping[str, th.Tensor], tailor_gates: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """``(actor latent, critic latent)``, each (B, L, decoder width): what the separate towers and
        decoders give for ``observations`` (preprocessed) and the actor's ``tailor_gates``, up to float rounding."""
        w = self._stacked(tailor_gates)
        robots = self._robot_constants(observations, w)
        actor = self.towers[0]
        tokens = th.where(
            robots["padding"], th.zeros((), dtype=w["embed_b"].dtype, device=w["embed_b"].device), observations[PROPRIOCEPTIVE]
        )
        batch, length, _ = tokens.shape
        d = actor.d_model
        x = F.linear(tokens, w["embed_proprio"]).view(batch, length, 2, d) + robots["embedding"]
        x = x.permute(2, 0, 1, 3).reshape(2, batch * length, d)  # (tower, B*L, d)
        mask = robots["mask"]
        for layer, lw in zip(actor.encoder.layers, w["layers"]):
            layer = cast(TransformerEncoderLayer, layer)
            heads, head_dim = layer.attention.n_heads, layer.attention.head_dim
            h = F.layer_norm(x, (d,), eps=layer.norm1.eps) * lw["norm1"][0] + lw["norm1"][1]
            qkv = _project(h, *lw["qkv"]).view(2 * batch, length, 3, heads, head_dim)
            q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)
            attended = F.scaled_dot_product_attention(q, k, v, attn_mask=mask).transpose(1, 2).reshape(2, batch * length, d)
            x = x + _project(attended, *lw["o"])
            h = F.layer_norm(x, (d,), eps=layer.norm2.eps) * lw["norm2"][0] + lw["norm2"][1]
            x = x + _project(layer.activation(_project(h, *lw["ff_in"])), *lw["ff_out"])
        features = x.view(2, batch, length, d)
        if len(actor.exteroception):
            encodings = []
            for key_name, stacked in w["extero"].items():
                flat = observations[key_name].flatten(1)
                if stacked is None:
                    critic = self.towers[1]
                    e = th.stack([actor.exteroception[key_name](flat, tailor_gates), critic.exteroception[key_name](flat)])
                else:
                    (first_w, first_b), rest = stacked
                    e = F.relu(F.linear(flat, first_w, first_b))  # (B, 2 * width)
                    e = e.view(batch, 2, -1).transpose(0, 1)
                    for weight, bias in rest:
                        e = F.relu(th.baddbmm(bias, e, weight))
                encodings.append(e)
            extero = th.cat(encodings, dim=-1)  # (2, B, E)
            features = th.cat([features, extero[:, :, None, :].expand(-1, -1, length, -1)], dim=-1)
        latent = features.reshape(2, batch * length, -1)
        for (weight, bias), activation in zip(w["decoder"], self.decoders[0].activations):
            latent = activation(_project(latent, weight, bias))
        latent = latent.view(2, batch, length, -1)
        return latent[0], latent[1]
