"""Pre-LayerNorm Transformer encoder whose projections can be dense or factorized.

``nn.MultiheadAttention`` owns its (fused) projection weights, so it cannot run factorized ones; this
module builds q, k, v, o and the two FFN matrices through a :class:`~sb3_divmorph.nn.layers.LinearBuilder`
and threads the per-sample tailor gates through every one of them.

Padding: ``key_padding_mask`` (True = padded token) removes padded tokens as attention keys, so a
padded token can never change a real token's output. Padded tokens still produce (meaningless)
outputs of their own, identical in train and eval mode; every consumer must mask them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_divmorph.nn.layers import LinearBuilder, project_many

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


class TransformerEncoder(nn.Module):
    """A stack of pre-LN layers, with no final norm (as in MetaMorph).

    :param d_model: token width.
    :param n_layers: number of layers.
    :param n_heads: attention heads.
    :param ff_dim: FFN hidden width.
    :param builder: builds every projection (dense or factorized).
    :param dropout: see :class:`TransformerEncoderLayer`.
    :param activation: see :class:`TransformerEncoderLayer`.
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
    ):
        super().__init__()
        builder = builder or LinearBuilder()
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
        for layer in self.layers:
            x = layer(x, mask, tailor_gates)
        return x


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
        return self.dropout(self.linear(tokens) * self.scale + self.position)
