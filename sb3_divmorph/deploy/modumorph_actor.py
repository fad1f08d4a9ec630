"""ModuMorph deployed for one robot and task: :class:`ModuMorphActor`.

The same folding rules as :class:`~sb3_divmorph.deploy.compact.CompactActor`: the weights the
hypernetworks generate for the robot and the fixed attention matrices (they depend on the robot
only) are constants and are stored as such; context encoders, hypernetworks and critic are dropped.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_divmorph.deploy.deployment import DeployedActor
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, PROPRIOCEPTIVE
from sb3_divmorph.policies.modumorph import ContextDecoder, ModuMorphExtractor, ModuMorphLayer, ModuMorphPolicy, RobotBatch


class PerLimbLinear(nn.Module):
    """``y_l = x_l W_l + b_l`` with one stored (in, out) matrix per real limb (generated weights, folded).

    :param weight: (n, in, out).
    :param bias: (n, out).
    """

    def __init__(self, weight: th.Tensor, bias: th.Tensor):
        super().__init__()
        self.weight = nn.Parameter(weight.detach().clone(), requires_grad=False)
        self.bias = nn.Parameter(bias.detach().clone(), requires_grad=False)

    def forward(self, x: th.Tensor) -> th.Tensor:
        # (B, n, in) -> (n, B, in) @ (n, in, out): one batched matmul per limb
        return (x.transpose(0, 1) @ self.weight).transpose(0, 1) + self.bias


def _frozen(module: nn.Module) -> nn.Module:
    module = copy.deepcopy(module)
    for p in module.parameters():
        p.requires_grad_(False)
    return module


class _FoldedLayer(nn.Module):
    """A ModuMorph layer for one robot: fixed attention is a stored (H, n, n) matrix."""

    def __init__(self, layer: ModuMorphLayer, weights: th.Tensor | None):
        super().__init__()
        self.n_heads, self.head_dim = layer.n_heads, layer.head_dim
        self.norm1, self.norm2 = _frozen(layer.norm1), _frozen(layer.norm2)
        self.v, self.o, self.ff_in, self.ff_out = (_frozen(getattr(layer, n)) for n in ("v", "o", "ff_in", "ff_out"))
        self.fixed = weights is not None
        if self.fixed:
            self.attention = nn.Parameter(weights.detach().clone(), requires_grad=False)
        else:
            self.q, self.k = _frozen(layer.q), _frozen(layer.k)
        self.gelu = layer.activation is F.gelu

    def _heads(self, x: th.Tensor) -> th.Tensor:
        return x.reshape(x.shape[0], x.shape[1], self.n_heads, self.head_dim).transpose(1, 2)

    def forward(self, x: th.Tensor) -> th.Tensor:
        h = self.norm1(x)
        if self.fixed:
            attended = self.attention @ self._heads(self.v(h))
        else:
            attended = F.scaled_dot_product_attention(self._heads(self.q(h)), self._heads(self.k(h)), self._heads(self.v(h)))
        x = x + self.o(attended.transpose(1, 2).reshape(x.shape))
        hidden = self.ff_in(self.norm2(x))
        return x + self.ff_out(F.gelu(hidden) if self.gelu else F.relu(hidden))


class ModuMorphActor(DeployedActor):
    """Deterministic actor of a :class:`ModuMorphPolicy` for one robot and task, everything robot-constant folded.

    Same interface as :class:`~sb3_divmorph.deploy.compact.CompactActor`:
    ``forward(proprioceptive, hfield, goal, object)`` on raw (B, 12, 52), (B, 1410), (B, 3),
    (B, 12) arrays -> (B, 24) action means (0 on padded slots). Build it with :meth:`from_policy`.
    """

    @classmethod
    @th.no_grad()
    def from_policy(
        cls,
        policy: ModuMorphPolicy,
        observation: Mapping[str, np.ndarray],
        observation_keys: tuple[str, ...],
        normalizer: Any | None = None,
    ) -> ModuMorphActor:
        """
        :param policy: a trained :class:`ModuMorphPolicy`.
        :param observation: one raw (unbatched) observation of the robot doing the task.
        :param observation_keys: the task's observations; encoders of the others are folded away.
        :param normalizer: the policy's ``VecNormalize`` (statistics baked in), or ``None``.
        """
        if not isinstance(policy, ModuMorphPolicy):
            raise TypeError(f"ModuMorphActor needs a ModuMorphPolicy, got {type(policy).__name__}")
        self = cls()
        policy = policy.cpu().eval()
        raw = {k: np.asarray(v, dtype=np.float32)[None] for k, v in observation.items()}
        obs = {k: th.as_tensor(v) for k, v in (raw if normalizer is None else normalizer.normalize_obs(raw)).items()}
        extractor: ModuMorphExtractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
        real = th.nonzero(obs[OBS_PADDING_MASK][0] < 0.5).flatten()
        self.register_buffer("real_tokens", real)
        self.n_tokens, self.slots = int(obs[OBS_PADDING_MASK].shape[1]), policy.slots_per_token
        self.used_extero = [k for k in extractor.exteroception.keys() if k in observation_keys]
        self.bake_normalization(normalizer, real, self.used_extero)

        context = obs[CONTEXT][:, real]
        robots = RobotBatch.from_context(context, extractor.hypernet_encoder) if extractor.hypernetwork else None
        if extractor.hypernetwork:
            weight, bias = extractor.embedding.generate(robots.embedding[0])
            self.embed = PerLimbLinear(weight * extractor.scale, bias * extractor.scale)
        else:
            proprio_dim = obs[PROPRIOCEPTIVE].shape[-1]
            w, b = extractor.embedding.weight, extractor.embedding.bias
            const = (b + context[0] @ w[:, proprio_dim:].T) * extractor.scale
            self.embed = PerLimbLinear((w[:, :proprio_dim].T * extractor.scale).expand(len(real), -1, -1), const)
        padding = th.zeros(1, len(real), dtype=th.bool)
        context_embedding = extractor.context_encoder(context) if extractor.fixed_attention else None
        self.blocks = nn.ModuleList(
            _FoldedLayer(
                layer, layer.attention_weights(layer.norm_context(context_embedding), padding)[0] if layer.fixed_attention else None
            )
            for layer in extractor.layers
        )
        self.exteroception = nn.ModuleDict({k: _frozen(extractor.exteroception[k]) for k in self.used_extero})

        # decoder: per-limb layers; encodings of absent observations join the first layer's bias
        decoder: ContextDecoder = policy.mlp_extractor.policy_net
        layers = []
        for layer in decoder.layers:
            if decoder.generated:
                w, b = layer.generate(robots.embedding[0])
            else:
                w, b = layer.weight.T.expand(len(real), -1, -1), layer.bias.expand(len(real), -1)
            layers.append([w, b])
        offset, keep = extractor.d_model, [th.arange(extractor.d_model)]
        w0, b0 = layers[0]
        b0 = b0.clone()
        for key, encoder in extractor.exteroception.items():
            width = encoder.out_dim
            if key in self.used_extero:
                keep.append(th.arange(offset, offset + width))
            else:
                value = encoder(obs[key].flatten(1))[0]
                b0 = b0 + th.einsum("i,nio->no", value, w0[:, offset : offset + width])
            offset += width
        layers[0] = [w0[:, th.cat(keep)], b0]
        self.decoder = nn.ModuleList(PerLimbLinear(w, b) for w, b in layers)
        self.decoder_activations = nn.ModuleList(_frozen(a) for a in decoder.activations)
        slot_real = (obs[ACT_PADDING_MASK][0] < 0.5).float().view(self.n_tokens, self.slots)
        self.register_buffer("action_scale", slot_real[real])
        return self.eval()

    def forward(self, proprioceptive: th.Tensor, hfield: th.Tensor, goal: th.Tensor, object: th.Tensor) -> th.Tensor:  # noqa: A002
        x = self.embed(self._normalize(PROPRIOCEPTIVE, proprioceptive.index_select(1, self.real_tokens)))
        for block in self.blocks:
            x = block(x)
        return self._fuse_and_decode(x, hfield, goal, object)
