"""Pre-LayerNorm Transformer encoder whose projections can be dense or factorized.

``nn.MultiheadAttention`` owns its (fused) projection weights, so it cannot run factorized ones; this
module builds q, k, v, o and the two FFN matrices through a :class:`~sb3_divmorph.nn.layers.LinearBuilder`
and threads the per-sample tailor gates through every one of them.

Padding: ``key_padding_mask`` (True = padded token) removes padded tokens as attention keys, so a
padded token can never change a real token's output. Padded tokens still produce (meaningless)
outputs of their own; every consumer must mask them.

Packing: while autograd records (the PPO update, distillation), the encoder runs its projections
and FFNs on the real tokens only (:class:`TokenPacking`) and pads them back just around attention.
The official robots fill 8.6 of the 12 token slots on average, so about a third of the update's
matmuls were spent on padding. Real tokens' outputs equal the padded path's up to float rounding;
padded tokens' outputs are then zero. Rollouts (no autograd, a handful of samples) keep the padded
path, where gathering would cost more than it saves.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple, cast

import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_divmorph.nn.layers import LinearBuilder, project_concat, project_many

#: FFN activations. Not in place: the FFN output is a view (``F.linear`` on tokens), and autograd
#: turns an in-place op on a view into extra copies of the whole (tokens x ff_dim) tensor.
ACTIVATIONS: dict[str, Callable[[th.Tensor], th.Tensor]] = {"relu": F.relu, "gelu": F.gelu}


def xavier_init(layer: nn.Linear) -> None:
    """Xavier-uniform weight, zero bias (PyTorch's init of attention in-projections)."""
    nn.init.xavier_uniform_(layer.weight)
    nn.init.zeros_(layer.bias)


def zero_bias_init(layer: nn.Linear) -> None:
    """Default weight, zero bias (PyTorch's init of the attention out-projection)."""
    nn.init.zeros_(layer.bias)


def attention_mask(key_padding_mask: th.Tensor) -> th.Tensor:
    """(B, L) True = padded  ->  (B, 1, 1, L) True = may attend, for ``scaled_dot_product_attention``.

    A sample whose tokens are all padded would give NaN (softmax over nothing); such a sample has no
    real token to protect, so it attends to everything instead.
    """
    allowed = ~key_padding_mask
    allowed = allowed | ~allowed.any(dim=-1, keepdim=True)
    return allowed[:, None, None, :]


class TokenPacking(NamedTuple):
    """Where the real tokens of a padded (B, L) batch are: packed row ``i`` is flat token ``flat_index[i]`` (``b * L + t``).

    :param flat_index: (N,) flat indices of the real tokens, in order.
    :param batch: B.
    :param length: L.
    """

    flat_index: th.Tensor
    batch: int
    length: int

    @classmethod
    def of(cls, key_padding_mask: th.Tensor) -> TokenPacking:
        """The packing of a (B, L) mask, True = padded."""
        batch, length = key_padding_mask.shape
        return cls((~key_padding_mask).flatten().nonzero().squeeze(1), batch, length)

    @property
    def sample(self) -> th.Tensor:
        """(N,) the sample each packed row belongs to."""
        return th.div(self.flat_index, self.length, rounding_mode="floor")

    @property
    def position(self) -> th.Tensor:
        """(N,) the token slot of each packed row."""
        return th.remainder(self.flat_index, self.length)

    def pack(self, x: th.Tensor) -> th.Tensor:
        """(B, L, D) -> (N, D): the real tokens' rows."""
        return x.reshape(-1, x.shape[-1]).index_select(0, self.flat_index)

    def unpack(self, rows: th.Tensor) -> th.Tensor:
        """(N, D) -> (B, L, D), padded tokens zero."""
        padded = rows.new_zeros(self.batch * self.length, rows.shape[-1])
        return padded.index_copy(0, self.flat_index, rows).view(self.batch, self.length, rows.shape[-1])


def packing_for(key_padding_mask: th.Tensor) -> TokenPacking | None:
    """The packing a pass should run with: while autograd records and some token is real, else
    ``None`` (the padded path: rollouts, or a batch of padding alone, which has nothing to pack)."""
    if not th.is_grad_enabled():
        return None
    packing = TokenPacking.of(key_padding_mask)
    return packing if packing.flat_index.numel() > 0 else None


class MultiHeadSelfAttention(nn.Module):
    """Multi-head self-attention with separately built q, k, v, o projections.

    :param d_model: token width.
    :param n_heads: number of heads (must divide ``d_model``).
    :param builder: builds the projections (dense or factorized).
    :param dropout: attention-weight dropout.
    :param name: prefix of the projections' names in errors.
    """

    def __init__(self, d_model: int, n_heads: int, builder: LinearBuilder, dropout: float = 0.0, name: str = "attention"):
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model={d_model} is not divisible by n_heads={n_heads}")
        self.n_heads = n_heads
        self.head_dim = d_model // n_heads
        self.dropout = dropout
        self.q = builder(d_model, d_model, xavier_init, name=f"{name}.q")
        self.k = builder(d_model, d_model, xavier_init, name=f"{name}.k")
        self.v = builder(d_model, d_model, xavier_init, name=f"{name}.v")
        self.o = builder(d_model, d_model, zero_bias_init, name=f"{name}.o")

    def _heads(self, x: th.Tensor) -> th.Tensor:
        batch, length, _ = x.shape
        return x.view(batch, length, self.n_heads, self.head_dim).transpose(1, 2)

    def forward(self, x: th.Tensor, attn_mask: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """
        :param x: (B, L, D) tokens.
        :param attn_mask: (B, 1, 1, L) boolean, True = may attend (see :func:`attention_mask`).
        :param tailor_gates: (B, N_m + N_t) or ``None``.
        """
        q, k, v = (self._heads(t) for t in project_many([self.q, self.k, self.v], x, tailor_gates))
        dropout = self.dropout if self.training else 0.0
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout)
        out = out.transpose(1, 2).reshape(x.shape)
        return self.o(out, tailor_gates)

    def forward_packed(self, rows: th.Tensor, packing: TokenPacking, attn_mask: th.Tensor, row_gates: th.Tensor | None) -> th.Tensor:
        """:meth:`forward` on packed real tokens (N, D); padded back only around the attention itself.

        :param row_gates: (N, N_m + N_t) each row's sample's gates, or ``None``.
        """
        width = rows.shape[-1]
        qkv = packing.unpack(project_concat([self.q, self.k, self.v], rows, row_gates))
        qkv = qkv.view(packing.batch, packing.length, 3, self.n_heads, self.head_dim)
        q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)
        dropout = self.dropout if self.training else 0.0
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout)
        out = out.transpose(1, 2).reshape(-1, width).index_select(0, packing.flat_index)
        return self.o(out, row_gates)


class TransformerEncoderLayer(nn.Module):
    """Pre-LN block: ``x + MSA(LN(x))`` then ``x + FFN(LN(x))`` (MetaMorph's layout).

    :param d_model: token width.
    :param n_heads: attention heads.
    :param ff_dim: FFN hidden width.
    :param builder: builds the six projections.
    :param dropout: dropout on attention weights and both residual branches.
    :param activation: FFN activation, ``"relu"`` (MetaMorph) or ``"gelu"``.
    :param name: prefix of the projections' names in errors.
    """

    def __init__(
        self,
        d_model: int,
        n_heads: int,
        ff_dim: int,
        builder: LinearBuilder,
        dropout: float = 0.0,
        activation: str = "relu",
        name: str = "transformer.0",
    ):
        super().__init__()
        self.attention = MultiHeadSelfAttention(d_model, n_heads, builder, dropout, name=f"{name}.attention")
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.ff_in = builder(d_model, ff_dim, name=f"{name}.ff_in")
        self.ff_out = builder(ff_dim, d_model, name=f"{name}.ff_out")
        self.dropout = nn.Dropout(dropout)
        self.activation = ACTIVATIONS[activation]

    def forward(self, x: th.Tensor, attn_mask: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        x = x + self.dropout(self.attention(self.norm1(x), attn_mask, tailor_gates))
        hidden = self.activation(self.ff_in(self.norm2(x), tailor_gates))
        return x + self.dropout(self.ff_out(hidden, tailor_gates))

    def forward_packed(self, rows: th.Tensor, packing: TokenPacking, attn_mask: th.Tensor, row_gates: th.Tensor | None) -> th.Tensor:
        """:meth:`forward` on packed real tokens (N, D) (see :class:`TokenPacking`)."""
        rows = rows + self.dropout(self.attention.forward_packed(self.norm1(rows), packing, attn_mask, row_gates))
        hidden = self.activation(self.ff_in(self.norm2(rows), row_gates))
        return rows + self.dropout(self.ff_out(hidden, row_gates))


class TransformerEncoder(nn.Module):
    """A stack of pre-LN layers, with no final norm (as in MetaMorph).

    :param d_model: token width.
    :param n_layers: number of layers.
    :param n_heads: attention heads.
    :param ff_dim: FFN hidden width.
    :param builder: builds every projection (dense or factorized).
    :param dropout: see :class:`TransformerEncoderLayer`.
    :param activation: see :class:`TransformerEncoderLayer`.
    :param pack_tokens: run on the real tokens only while autograd records (see the module docstring).
    """

    def __init__(
        self,
        d_model: int,
        n_layers: int,
        n_heads: int,
        ff_dim: int,
        builder: LinearBuilder | None = None,
        dropout: float = 0.0,
        activation: str = "relu",
        pack_tokens: bool = True,
    ):
        super().__init__()
        builder = builder or LinearBuilder()
        self.pack_tokens = pack_tokens
        self.layers = nn.ModuleList(
            TransformerEncoderLayer(d_model, n_heads, ff_dim, builder, dropout, activation, name=f"transformer.{i}")
            for i in range(n_layers)
        )

    def forward(self, x: th.Tensor, key_padding_mask: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """
        :param x: (B, L, D) tokens.
        :param key_padding_mask: (B, L) boolean, True = padded.
        :param tailor_gates: (B, N_m + N_t) or ``None``.
        :return: (B, L, D).
        """
        mask = attention_mask(key_padding_mask)
        packing = packing_for(key_padding_mask) if self.pack_tokens else None
        if packing is not None:
            rows = packing.pack(x)
            row_gates = None if tailor_gates is None else tailor_gates.index_select(0, packing.sample)
            return packing.unpack(self.forward_rows(rows, packing, mask, row_gates))
        for layer in self.layers:
            x = layer(x, mask, tailor_gates)
        return x

    def forward_rows(self, rows: th.Tensor, packing: TokenPacking, attn_mask: th.Tensor, row_gates: th.Tensor | None) -> th.Tensor:
        """The encoder on packed real tokens: (N, D) -> (N, D) (see :class:`TokenPacking`).

        :param attn_mask: (B, 1, 1, L) from :func:`attention_mask`.
        :param row_gates: (N, N_m + N_t) each row's sample's gates, or ``None``.
        """
        for block in cast(list[TransformerEncoderLayer], list(self.layers)):
            rows = block.forward_packed(rows, packing, attn_mask, row_gates)
        return rows


class TokenEmbedding(nn.Module):
    """Shared per-token linear embedding times sqrt(d), plus a learnt position embedding.

    MetaMorph's init: weight U(-0.1, 0.1), position embedding N(0, 1).

    :param in_dim: per-token input features.
    :param d_model: token width.
    :param max_tokens: sequence length.
    :param dropout: dropout after adding the position embedding.
    """

    def __init__(self, in_dim: int, d_model: int, max_tokens: int, dropout: float = 0.0):
        super().__init__()
        self.linear = nn.Linear(in_dim, d_model)
        nn.init.uniform_(self.linear.weight, -0.1, 0.1)
        self.position = nn.Parameter(th.randn(max_tokens, d_model))
        self.scale = math.sqrt(d_model)
        self.dropout = nn.Dropout(dropout)

    def forward(self, tokens: th.Tensor) -> th.Tensor:
        """(B, L, in_dim) -> (B, L, d_model)."""
        return self.dropout(self.linear(tokens) * self.scale + self.position)

    def forward_rows(self, rows: th.Tensor, position: th.Tensor) -> th.Tensor:
        """:meth:`forward` on packed tokens: (N, in_dim) rows in the token slots ``position`` (N,) -> (N, d_model)."""
        return self.dropout(self.linear(rows) * self.scale + self.position.index_select(0, position))
