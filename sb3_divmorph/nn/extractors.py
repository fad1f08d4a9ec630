"""Features extractor of the morphology-aware Transformer: observation dict -> per-token features.

Tokens (one per limb, torso first) are ``proprioceptive`` (+ ``context``) rows, embedded, mixed by a
Transformer under the key-padding mask, then fused late with the exteroception encodings (the same
vectors appended to every token), as in MetaMorph. The output is (B, L, features_dim): SB3 only
uses ``features_dim`` to size the heads, so token features pass through unchanged.
"""

from __future__ import annotations

from typing import Any
from collections.abc import Mapping, Sequence

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from sb3_divmorph.nn.layers import Factorization, LinearBuilder
from sb3_divmorph.nn.transformer import TokenEmbedding, TokenPacking, TransformerEncoder, attention_mask

PROPRIOCEPTIVE = "proprioceptive"
CONTEXT = "context"
OBS_PADDING_MASK = "obs_padding_mask"
ACT_PADDING_MASK = "act_padding_mask"
TASK_EMBEDDING = "task_embedding"
#: Global (non-token) observation keys that can be fused into every token.
EXTEROCEPTION_KEYS = ("hfield", "goal", "object")


def token_padding(observations: Mapping[str, th.Tensor]) -> th.Tensor:
    """(B, L) boolean, True = padded token (``obs_padding_mask`` is 1.0 for padding)."""
    return observations[OBS_PADDING_MASK] > 0.5


class ExteroceptionEncoder(nn.Sequential):
    """MLP with ReLU after every layer (MetaMorph's height-map encoder 1410 -> 64 -> 64).

    Built dense by default; with a factorizing ``builder`` its layers are diverted like the
    Transformer's (DivMorph's ``divert_exteroception``), so deployment can prune them too.

    :param in_dim: flat input size.
    :param dims: layer widths.
    :param builder: builds each layer (default: dense ``nn.Linear``-compatible layers).
    :param name: prefix of the layers' names in errors.
    """

    def __init__(self, in_dim: int, dims: Sequence[int], builder: LinearBuilder | None = None, name: str = "exteroception"):
        builder = builder or LinearBuilder()
        layers: list[nn.Module] = []
        for i, out_dim in enumerate(dims):
            layers += [builder(in_dim, out_dim, name=f"{name}.{i}"), nn.ReLU()]
            in_dim = out_dim
        super().__init__(*layers)
        self.out_dim = in_dim

    def forward(self, x: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """
        :param x: (B, in_dim).
        :param tailor_gates: (B, G_m + G_t) gates for diverted layers, or ``None``.
        """
        for module in self:
            x = module(x) if isinstance(module, nn.ReLU) else module(x, tailor_gates)
        return x


class MorphologyTransformerExtractor(BaseFeaturesExtractor):
    """Token embedding + pre-LN Transformer encoder + late exteroception fusion.

    :param observation_space: the UNIMAL ``spaces.Dict`` (see ``unimal_envs.contract``).
    :param d_model: token width.
    :param n_layers: Transformer layers.
    :param n_heads: attention heads.
    :param ff_dim: FFN width.
    :param dropout: Transformer dropout. Default 0: SB3 collects rollouts in eval mode and trains
        in train mode, so any dropout makes the PPO ratio differ from 1 on the first epoch.
    :param embedding_dropout: dropout after the position embedding (MetaMorph: 0.1), same caveat.
    :param activation: FFN activation (``"relu"`` as in MetaMorph, or ``"gelu"``).
    :param use_context: append the static ``context`` row to each token's input.
    :param exteroception: ``{obs key: MLP widths}``; keys absent from the space are skipped.
    :param factorization: plain-valued :class:`~sb3_divmorph.nn.layers.Factorization` fields
        (``n_morph_tailors``, ``n_task_tailors``, ``orthogonal``, ``divert``, ``n_learngenes``), or
        ``None`` for dense projections.
    :param factorize_exteroception: build the exteroception encoders with the same factorization
        (diverted like the Transformer); default: dense encoders.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        d_model: int = 64,
        n_layers: int = 2,
        n_heads: int = 2,
        ff_dim: int = 256,
        dropout: float = 0.0,
        embedding_dropout: float = 0.0,
        activation: str = "relu",
        use_context: bool = True,
        exteroception: Mapping[str, Sequence[int]] | None = None,
        factorization: Mapping[str, Any] | None = None,
        factorize_exteroception: bool = False,
    ):
        proprio_shape = observation_space[PROPRIOCEPTIVE].shape
        assert proprio_shape is not None  # a Box: the contract's spaces always have a shape
        self.max_tokens = proprio_shape[0]
        self.use_context = use_context and CONTEXT in observation_space.spaces
        context_shape = observation_space[CONTEXT].shape if self.use_context else None
        token_dim = proprio_shape[1] + (context_shape[1] if context_shape else 0)

        extero = {
            key: list(dims) for key, dims in sorted((exteroception or {}).items()) if key in observation_space.spaces and len(dims) > 0
        }
        builder = LinearBuilder(Factorization(**factorization) if factorization else None)
        extero_builder = builder if factorize_exteroception else LinearBuilder()
        encoders = {
            key: ExteroceptionEncoder(
                int(th.tensor(observation_space[key].shape).prod()), dims, extero_builder, name=f"exteroception.{key}"
            )
            for key, dims in extero.items()
        }
        extero_dim = sum(encoder.out_dim for encoder in encoders.values())
        super().__init__(observation_space, features_dim=d_model + extero_dim)

        self.d_model = d_model
        self.builder = builder
        self.embedding = TokenEmbedding(token_dim, d_model, self.max_tokens, embedding_dropout)
        self.encoder = TransformerEncoder(d_model, n_layers, n_heads, ff_dim, self.builder, dropout, activation)
        self.exteroception = nn.ModuleDict(encoders)

    @property
    def tailor_gates_size(self) -> int:
        """Size of the gate vector this extractor takes (0 = it takes none)."""
        return self.builder.tailor_gates_size

    def forward(self, observations: Mapping[str, th.Tensor], tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """
        :param observations: preprocessed observation dict.
        :param tailor_gates: (B, N_m + N_t), or ``None`` (dense network, or all units on).
        :return: (B, L, features_dim) token features; rows of padded tokens are meaningless.
        """
        padding = token_padding(observations)
        tokens = observations[PROPRIOCEPTIVE]
        if self.use_context:
            tokens = th.cat([tokens, observations[CONTEXT]], dim=-1)
        # VecNormalize makes padded rows non-zero; zero them so their content is never read at all.
        tokens = th.where(padding[..., None], th.zeros((), dtype=tokens.dtype, device=tokens.device), tokens)
        features = self.encoder(self.embedding(tokens), padding, tailor_gates)
        if len(self.exteroception):
            extero = self._exteroception(observations, tailor_gates)
            features = th.cat([features, extero[:, None, :].expand(-1, features.shape[1], -1)], dim=-1)
        return features

    def forward_rows(self, observations: Mapping[str, th.Tensor], tailor_gates: th.Tensor | None, packing: TokenPacking) -> th.Tensor:
        """:meth:`forward` on the real tokens only: (N, features_dim), packed row ``i`` the token
        ``packing.flat_index[i]``. The embedding, the Transformer's projections and FFNs (and whatever
        reads the features per token next) then never compute a padded slot (see :class:`TokenPacking`).

        :param packing: the real tokens of ``observations``' padding mask (:func:`packing_for`).
        """
        tokens = packing.pack(observations[PROPRIOCEPTIVE])
        if self.use_context:
            tokens = th.cat([tokens, packing.pack(observations[CONTEXT])], dim=-1)
        row_gates = None if tailor_gates is None else tailor_gates.index_select(0, packing.sample)
        rows = self.embedding.forward_rows(tokens, packing.position)
        rows = self.encoder.forward_rows(rows, packing, attention_mask(token_padding(observations)), row_gates)
        if len(self.exteroception):
            rows = th.cat([rows, self._exteroception(observations, tailor_gates).index_select(0, packing.sample)], dim=-1)
        return rows

    def _exteroception(self, observations: Mapping[str, th.Tensor], tailor_gates: th.Tensor | None) -> th.Tensor:
        """(B, sum of the encoders' widths): every exteroception encoding, side by side."""
        return th.cat([encoder(observations[key].flatten(1), tailor_gates) for key, encoder in self.exteroception.items()], dim=-1)
