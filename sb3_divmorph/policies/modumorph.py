"""ModuMorph (Xiong et al., ICML 2023): MetaMorph's Transformer made modular by the morphology context.

Two mechanisms, each switchable for ablation:

* **fixed attention** (``fixed_attention=True``): a context encoder (``Linear(C -> d)``, ReLU, then
  2 x ``Linear(d -> d)``, ReLU) runs once per robot and is shared by every layer. In every layer
  the query and key are projections of ``LayerNorm_ctx(context embedding)`` and only the value
  comes from the state (``norm1(x)``), so the attention weights depend on the morphology only.
* **hypernetwork** (``hypernetwork=True``): a second context encoder (``Linear(C -> h)``, ReLU,
  ``Linear(h -> h)``, ReLU) generates, per limb, the input-embedding weights and bias and the
  weights and bias of every decoder layer (hidden layers and the action / value head). Every
  generator starts with a zero weight matrix, so at init each limb gets the same generated
  parameters: the generator's bias, drawn U(-0.1, 0.1) for the embedding and U(-0.01, 0.01) for the
  decoder. The token input is then proprioception only: the context enters through the generated
  weights.

No position embedding and no embedding dropout (the authors' flags). The critic is a separate
network of the same kind (as in MetaMorph) unless ``share_features_extractor=True``.

Generated weights depend on the robot only, so they are computed once per distinct robot of a
batch (rows with identical ``context``) and gathered for its samples: a minibatch of many states
of few robots pays the hypernetworks' cost per robot, not per sample.

:class:`~sb3_divmorph.deploy.modumorph_actor.ModuMorphActor` is the deployment form for one robot
and task.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_divmorph.nn.decoders import small_uniform_init
from sb3_divmorph.nn.distributions import MaskedDiagGaussianDistribution
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, PROPRIOCEPTIVE, ExteroceptionEncoder, token_padding
from sb3_divmorph.nn.gates import masked_mean
from sb3_divmorph.nn.layers import DenseLinear
from sb3_divmorph.nn.transformer import ACTIVATIONS, xavier_init, zero_bias_init
from sb3_divmorph.policies.morphology_transformer import PRESET_SIZES, PRESETS, MorphologyTransformerPolicy

#: ModuMorph's extra sizes per preset (the Transformer sizes are MetaMorph's, ``PRESETS``).
MODUMORPH_PRESETS: dict[str, dict[str, Any]] = {
    "small": dict(hypernet_dim=64),
    "paper": dict(hypernet_dim=128),
}
#: init range of the generated input embedding and of the generated decoder (authors' values)
EMBEDDING_INIT = 0.1
DECODER_INIT = 0.01


def context_encoder(in_dim: int, width: int, n_layers: int) -> nn.Sequential:
    """``Linear(in -> width)``, ReLU, then ``n_layers - 1`` x (``Linear(width -> width)``, ReLU)."""
    layers: list[nn.Module] = []
    for i in range(n_layers):
        layers += [nn.Linear(in_dim if i == 0 else width, width), nn.ReLU()]
    return nn.Sequential(*layers)


class RobotBatch(NamedTuple):
    """Hypernetwork context of the distinct robots of a batch, and the batch's samples grouped by robot.

    :param embedding: (U, L, h) per-limb hypernetwork context of the U distinct robots.
    :param order: (B,) sample indices sorted by robot.
    :param counts: samples of each robot, in ``order``.
    :param restore: (B,) inverse permutation of ``order``.
    """

    embedding: th.Tensor
    order: th.Tensor
    counts: list[int]
    restore: th.Tensor

    @classmethod
    def from_context(cls, context: th.Tensor, encoder, padding: th.Tensor | None = None) -> RobotBatch:
        """Group a (B, L, C) context batch (padded rows already zeroed) by robot and encode each robot once.

        :param context: (B, L, C) static per-token features.
        :param encoder: called as ``encoder(context)`` on the (U, L, C) distinct robots, or as
            ``encoder(context, padding)`` when ``padding`` is given.
        :param padding: (B, L) True = padded token, or ``None``; part of what makes robots distinct.
        """
        key = context.flatten(1) if padding is None else th.cat([context.flatten(1), padding.to(context.dtype)], dim=1)
        unique, inverse = th.unique(key, dim=0, return_inverse=True)
        order = th.argsort(inverse, stable=True)
        counts = th.bincount(inverse, minlength=len(unique)).tolist()
        width = context.shape[1] * context.shape[2]
        unique_context = unique[:, :width].view(-1, *context.shape[1:])
        if padding is None:
            embedding = encoder(unique_context)
        else:
            embedding = encoder(unique_context, unique[:, width:] > 0.5)
        return cls(embedding, order, counts, th.argsort(order))

    def apply(self, x: th.Tensor, weight: th.Tensor, bias: th.Tensor) -> th.Tensor:
        """``y[b, l] = x[b, l] @ weight[robot(b), l] + bias[robot(b), l]`` without building per-sample weights.

        :param x: (B, L, in); ``weight``: (U, L, in, out); ``bias``: (U, L, out).
        """
        if len(self.counts) == 1:
            return (x.transpose(0, 1) @ weight[0]).transpose(0, 1) + bias[0]
        groups = x[self.order].split(self.counts)
        # unbind, not weight[u]: each index's backward would allocate a gradient of all U robots' weights
        out = [(g.transpose(0, 1) @ w).transpose(0, 1) + b for g, w, b in zip(groups, weight.unbind(0), bias.unbind(0))]
        return th.cat(out)[self.restore]


class HyperLinear(nn.Module):
    """A per-limb linear layer whose weight and bias are generated from the limb's context.

    ``y_l = x_l W(h_l) + b(h_l)`` for every token ``l``; ``W(h) = G_w h + c_w`` reshaped to
    ``(in, out)``. ``G_w`` and ``G_b`` start at zero and ``c_w``, ``c_b`` are drawn
    U(-init_range, init_range), so at init every limb of every robot has the same layer.

    :param in_dim: input features per token.
    :param out_dim: output features per token.
    :param hypernet_dim: width of the hypernetwork context.
    :param init_range: range of the uniform init of the generated weight and bias.
    """

    def __init__(self, in_dim: int, out_dim: int, hypernet_dim: int, init_range: float):
        super().__init__()
        self.in_dim, self.out_dim = in_dim, out_dim
        self.weight_generator = nn.Linear(hypernet_dim, in_dim * out_dim)
        self.bias_generator = nn.Linear(hypernet_dim, out_dim)
        for generator in (self.weight_generator, self.bias_generator):
            nn.init.zeros_(generator.weight)
            nn.init.uniform_(generator.bias, -init_range, init_range)

    def generate(self, embedding: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """(..., h) -> weights (..., in, out) and biases (..., out)."""
        weight = self.weight_generator(embedding).view(*embedding.shape[:-1], self.in_dim, self.out_dim)
        return weight, self.bias_generator(embedding)

    def forward(self, x: th.Tensor, robots: RobotBatch) -> th.Tensor:
        """
        :param x: (B, L, in) tokens.
        :param robots: the batch's distinct robots (see :class:`RobotBatch`).
        :return: (B, L, out).
        """
        weight, bias = self.generate(robots.embedding)
        return robots.apply(x, weight, bias)


class ModuMorphLayer(nn.Module):
    """Pre-LN Transformer layer with (optionally) context-fixed attention.

    Attention weights are computed explicitly (L is at most a dozen limbs) and returned, so that
    analysis sees exactly the weights the forward pass used.

    :param d_model: token width.
    :param n_heads: attention heads.
    :param ff_dim: FFN width.
    :param fixed_attention: query and key from the normalised context embedding (ModuMorph);
        False: from ``norm1(x)`` (MetaMorph).
    :param dropout: dropout on attention weights and both residual branches.
    :param activation: FFN activation.
    """

    def __init__(self, d_model: int, n_heads: int, ff_dim: int, fixed_attention: bool, dropout: float = 0.0, activation: str = "relu"):
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model={d_model} is not divisible by n_heads={n_heads}")
        self.n_heads, self.head_dim = n_heads, d_model // n_heads
        self.fixed_attention = fixed_attention
        self.q, self.k, self.v = (DenseLinear(d_model, d_model) for _ in range(3))
        self.o = DenseLinear(d_model, d_model)
        for layer in (self.q, self.k, self.v):
            xavier_init(layer)
        zero_bias_init(self.o)
        self.norm_context = nn.LayerNorm(d_model) if fixed_attention else None
        self.norm1, self.norm2 = nn.LayerNorm(d_model), nn.LayerNorm(d_model)
        self.ff_in, self.ff_out = DenseLinear(d_model, ff_dim), DenseLinear(ff_dim, d_model)
        self.dropout = nn.Dropout(dropout)
        self.activation = ACTIVATIONS[activation]

    def _heads(self, x: th.Tensor) -> th.Tensor:
        return x.view(x.shape[0], x.shape[1], self.n_heads, self.head_dim).transpose(1, 2)

    def attention_weights(self, query_key_input: th.Tensor, key_padding_mask: th.Tensor) -> th.Tensor:
        """(B, H, L, L) softmax weights; padded keys get 0 (a robot of only padding attends to all)."""
        q, k = self._heads(self.q(query_key_input)), self._heads(self.k(query_key_input))
        scores = q @ k.transpose(-1, -2) / math.sqrt(self.head_dim)
        allowed = ~key_padding_mask
        allowed = allowed | ~allowed.any(-1, keepdim=True)
        scores = scores.masked_fill(~allowed[:, None, None, :], float("-inf"))
        return scores.softmax(-1)

    def forward(self, x: th.Tensor, context: th.Tensor | None, key_padding_mask: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        :param x: (B, L, D) state tokens.
        :param context: (B, L, D) context embedding (fixed attention), else ``None``.
        :param key_padding_mask: (B, L) True = padded.
        :return: new tokens (B, L, D) and the attention weights (B, H, L, L).
        """
        h = self.norm1(x)
        weights = self.attention_weights(self.norm_context(context) if self.fixed_attention else h, key_padding_mask)
        attended = self.dropout(weights) @ self._heads(self.v(h))
        x = x + self.dropout(self.o(attended.transpose(1, 2).reshape(x.shape)))
        return x + self.dropout(self.ff_out(self.activation(self.ff_in(self.norm2(x))))), weights


class ModuMorphFeatures(NamedTuple):
    """Output of :class:`ModuMorphExtractor`: token features and the robots' hypernetwork context."""

    tokens: th.Tensor  # (B, L, features_dim)
    robots: RobotBatch | None  # None without the hypernetwork


class ModuMorphExtractor(BaseFeaturesExtractor):
    """Embedding (generated per limb, or shared) + Transformer with fixed attention + late exteroception.

    :param observation_space: the UNIMAL ``spaces.Dict``.
    :param d_model: token width.
    :param n_layers: Transformer layers.
    :param n_heads: attention heads.
    :param ff_dim: FFN width.
    :param fixed_attention: see :class:`ModuMorphLayer`.
    :param hypernetwork: generate the input embedding per limb from the context.
    :param hypernet_dim: width of the hypernetwork's context encoder.
    :param dropout: Transformer dropout (default 0, see MetaMorph's extractor).
    :param activation: FFN activation.
    :param exteroception: ``{obs key: MLP widths}``; keys absent from the space are skipped.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        d_model: int = 64,
        n_layers: int = 2,
        n_heads: int = 2,
        ff_dim: int = 256,
        fixed_attention: bool = True,
        hypernetwork: bool = True,
        hypernet_dim: int = 64,
        dropout: float = 0.0,
        activation: str = "relu",
        exteroception: Mapping[str, Sequence[int]] | None = None,
    ):
        proprio_dim = observation_space[PROPRIOCEPTIVE].shape[1]
        n_context = observation_space[CONTEXT].shape[1]
        extero = {k: list(v) for k, v in sorted((exteroception or {}).items()) if k in observation_space.spaces and len(v) > 0}
        encoders = {k: ExteroceptionEncoder(int(np.prod(observation_space[k].shape)), dims) for k, dims in extero.items()}
        super().__init__(observation_space, features_dim=d_model + sum(e.out_dim for e in encoders.values()))
        self.d_model, self.scale = d_model, math.sqrt(d_model)
        self.fixed_attention, self.hypernetwork = fixed_attention, hypernetwork
        # its output is the query/key input of every layer, hence width d_model
        self.context_encoder = context_encoder(n_context, d_model, 3) if fixed_attention else None
        self.hypernet_encoder = context_encoder(n_context, hypernet_dim, 2) if hypernetwork else None
        if hypernetwork:
            self.embedding: nn.Module = HyperLinear(proprio_dim, d_model, hypernet_dim, EMBEDDING_INIT)
        else:
            # MetaMorph's token embedding (proprioception + context), without the position embedding
            self.embedding = nn.Linear(proprio_dim + n_context, d_model)
            nn.init.uniform_(self.embedding.weight, -EMBEDDING_INIT, EMBEDDING_INIT)
        self.layers = nn.ModuleList(ModuMorphLayer(d_model, n_heads, ff_dim, fixed_attention, dropout, activation) for _ in range(n_layers))
        self.exteroception = nn.ModuleDict(encoders)

    def forward(self, observations: Mapping[str, th.Tensor], return_attention: bool = False):
        """
        :param observations: preprocessed observation dict.
        :param return_attention: also return every layer's (B, H, L, L) attention weights.
        :return: :class:`ModuMorphFeatures` (and the list of attention weights).
        """
        padding = token_padding(observations)
        zero = th.zeros((), dtype=observations[PROPRIOCEPTIVE].dtype, device=padding.device)
        # padded rows may hold anything (VecNormalize, NaN): zero them so they are never read
        proprio = th.where(padding[..., None], zero, observations[PROPRIOCEPTIVE])
        context = th.where(padding[..., None], zero, observations[CONTEXT])
        robots = None
        if self.hypernetwork:
            robots = RobotBatch.from_context(context, self.hypernet_encoder)
            x = self.embedding(proprio, robots) * self.scale
        else:
            x = self.embedding(th.cat([proprio, context], dim=-1)) * self.scale
        context_embedding = self.context_encoder(context) if self.fixed_attention else None
        attention = []
        for layer in self.layers:
            x, weights = layer(x, context_embedding, padding)
            attention.append(weights)
        if len(self.exteroception):
            extero = th.cat([enc(observations[k].flatten(1)) for k, enc in self.exteroception.items()], dim=-1)
            x = th.cat([x, extero[:, None, :].expand(-1, x.shape[1], -1)], dim=-1)
        features = ModuMorphFeatures(x, robots)
        return (features, attention) if return_attention else features


class ContextDecoder(nn.Module):
    """Per-token decoder MLP and output head; every layer generated per limb with the hypernetwork.

    :param in_dim: token feature size.
    :param dims: hidden widths.
    :param out_dim: outputs per token (action slots, or 1 for the value).
    :param activation_fn: activation class after each hidden layer.
    :param hypernet_dim: hypernetwork context width, or ``None`` for shared dense layers (MetaMorph's).
    """

    def __init__(self, in_dim: int, dims: Sequence[int], out_dim: int, activation_fn: type[nn.Module], hypernet_dim: int | None):
        super().__init__()
        sizes = [in_dim, *dims, out_dim]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
            if hypernet_dim is not None:
                layers.append(HyperLinear(a, b, hypernet_dim, DECODER_INIT))
            else:
                layer = DenseLinear(a, b)
                if i == len(sizes) - 2:
                    small_uniform_init(layer)
                layers.append(layer)
        self.layers = nn.ModuleList(layers)
        self.activations = nn.ModuleList([activation_fn() for _ in dims] + [nn.Identity()])
        self.generated = hypernet_dim is not None

    def forward(self, x: th.Tensor, robots: RobotBatch | None) -> th.Tensor:
        for layer, activation in zip(self.layers, self.activations):
            x = activation(layer(x, robots) if self.generated else layer(x))
        return x


class ModuMorphDecoder(nn.Module):
    """SB3 ``mlp_extractor`` of ModuMorph: the actor's and the critic's per-limb decoders, heads included."""

    def __init__(self, policy_net: ContextDecoder, value_net: ContextDecoder):
        super().__init__()
        self.policy_net, self.value_net = policy_net, value_net
        self.latent_dim_pi = policy_net.layers[-1].out_dim if policy_net.generated else policy_net.layers[-1].out_features
        self.latent_dim_vf = 1


class ModuMorphPolicy(MorphologyTransformerPolicy):
    """ModuMorph: MetaMorph's Transformer with fixed attention and a context hypernetwork.

    Same observation/action contract, masked Gaussian (fixed std 0.9 by default), value = masked
    mean of per-token values, and separate actor and critic networks as :class:`MetaMorphPolicy`.

    :param fixed_attention: attention weights from the morphology context only (ablation: False).
    :param hypernetwork: per-limb generated input embedding and decoder (ablation: False).
    :param hypernet_dim: width of the hypernetwork's context encoder.

    Other arguments: see :class:`~sb3_divmorph.policies.MorphologyTransformerPolicy`
    (``use_context`` and ``embedding_dropout`` do not apply: the context always enters, and there
    is no position embedding to drop out).
    """

    preset_table = {name: {**PRESETS[name], **MODUMORPH_PRESETS[PRESET_SIZES[name]]} for name in PRESETS}
    # its extractor returns a structure (tokens, robot context) that the autocast path does not cast back
    supports_mixed_precision = False
    _modumorph_keys = ("fixed_attention", "hypernetwork", "hypernet_dim")
    _config_keys = MorphologyTransformerPolicy._config_keys + _modumorph_keys

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        preset: str = "small",
        fixed_attention: bool = True,
        hypernetwork: bool = True,
        hypernet_dim: int | None = None,
        **kwargs: Any,
    ):
        if kwargs.get("embedding_dropout"):
            raise ValueError("ModuMorph has no position embedding, so no embedding dropout")
        self._modumorph_explicit = dict(fixed_attention=fixed_attention, hypernetwork=hypernetwork, hypernet_dim=hypernet_dim)
        kwargs.setdefault("features_extractor_class", ModuMorphExtractor)
        super().__init__(observation_space, action_space, lr_schedule, preset=preset, **kwargs)

    def _extra_explicit(self) -> dict[str, Any]:
        return self._modumorph_explicit

    def _extractor_kwargs(self) -> dict[str, Any]:
        c = self.config
        return dict(
            d_model=c["d_model"],
            n_layers=c["n_layers"],
            n_heads=c["n_heads"],
            ff_dim=c["ff_dim"],
            fixed_attention=c["fixed_attention"],
            hypernetwork=c["hypernetwork"],
            hypernet_dim=c["hypernet_dim"],
            dropout=c["dropout"],
            activation=c["transformer_activation"],
            exteroception=c["exteroception"],
        )

    def _build(self, lr_schedule: Schedule) -> None:
        # As the base class, except that the action and value heads are the last layers of the
        # per-limb decoders (generated per limb): action_net / value_net are pass-throughs.
        self.action_dist = MaskedDiagGaussianDistribution(int(np.prod(self.action_space.shape)))
        self._build_mlp_extractor()
        self.action_net = nn.Identity()
        self.value_net = nn.Identity()
        log_std = th.full((self.action_dist.action_dim,), math.log(self.action_std))
        if self.learn_std:
            self.log_std = nn.Parameter(log_std)
        else:
            self.register_buffer("log_std", log_std)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]

    def _build_mlp_extractor(self) -> None:
        hypernet = self.config["hypernet_dim"] if self.config["hypernetwork"] else None
        if isinstance(self.net_arch, dict):
            pi, vf = self.net_arch.get("pi", []), self.net_arch.get("vf", [])
        else:
            pi = vf = self.net_arch
        self.mlp_extractor = ModuMorphDecoder(
            ContextDecoder(self.features_dim, pi, self.slots_per_token, self.activation_fn, hypernet),
            ContextDecoder(self.features_dim, vf, 1, self.activation_fn, hypernet),
        )

    def _latents(self, obs, actor: bool = True, critic: bool = True):
        if self.share_features_extractor:
            pi_features = vf_features = self.features_extractor(obs)
        else:
            pi_features = self.pi_features_extractor(obs) if actor else None
            vf_features = self.vf_features_extractor(obs) if critic else None
        latent_pi = self.mlp_extractor.policy_net(pi_features.tokens, pi_features.robots) if actor else None
        latent_vf = self.mlp_extractor.value_net(vf_features.tokens, vf_features.robots) if critic else None
        return latent_pi, latent_vf, None

    def _distribution(self, latent_pi: th.Tensor, obs: Mapping[str, th.Tensor], gates: th.Tensor | None):
        return self.action_dist.proba_distribution(latent_pi.flatten(1), self.log_std, obs[ACT_PADDING_MASK])

    def _value(self, latent_vf: th.Tensor, obs: Mapping[str, th.Tensor], gates: th.Tensor | None) -> th.Tensor:
        return masked_mean(latent_vf, token_padding(obs))

    def extract_features(self, obs: PyTorchObs, features_extractor: nn.Module | None = None):
        """:class:`ModuMorphFeatures`; a (pi, vf) tuple when the extractor is not shared (SB3's API)."""
        obs = self._preprocess(obs)
        if self.share_features_extractor or features_extractor is not None:
            return (features_extractor or self.features_extractor)(obs)
        return self.pi_features_extractor(obs), self.vf_features_extractor(obs)

    def attention_weights(self, observation: PyTorchObs, actor: bool = True) -> list[th.Tensor]:
        """Every layer's (B, H, L, L) attention weights in the actor's (or critic's) Transformer, no grad."""
        if isinstance(next(iter(observation.values())), np.ndarray):
            observation, _ = self.obs_to_tensor(observation)  # type: ignore[arg-type]
        extractor = (
            self.features_extractor
            if self.share_features_extractor
            else (self.pi_features_extractor if actor else self.vf_features_extractor)
        )
        with th.no_grad():
            return extractor(self._preprocess(observation), return_attention=True)[1]

    def _extractor_parts(self, prefix: str, extractor: nn.Module, count) -> dict[str, int]:
        """Parameters per part: context encoders, hypernetwork-generated layers, Transformer."""
        return {
            f"{prefix}/embedding": count(extractor.embedding),
            f"{prefix}/context_encoder": count(extractor.context_encoder),
            f"{prefix}/hypernet_encoder": count(extractor.hypernet_encoder),
            f"{prefix}/transformer": count(extractor.layers),
            f"{prefix}/exteroception": count(extractor.exteroception),
        }
