"""Morphology- and task-aware gates of DivMorph: ``softmax(TopK(G(e), k))``.

A :class:`MorphologyEncoder` turns the static per-token ``context`` of a robot into one morphology
embedding ``e_m``; the task embedding ``e_t`` is the sentence embedding of the task instruction
(an observation key). Two :class:`TopKSoftGate` s map them to sparse soft weights over the
morphology and task tailors, and :class:`DiversionRouter` bundles the three.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch as th
from torch import nn

from sb3_divmorph.nn.transformer import TokenEmbedding, TransformerEncoder


class TopKSoftGate(nn.Module):
    """``softmax(TopK(G(e), k))``: exactly ``k`` non-zero weights that sum to 1.

    Scores outside the top ``k`` are set to ``-inf`` before the softmax, so their weights are exact
    zeros (the tailors they gate can be pruned) and only the kept scores receive gradient. With
    ``k = 1`` the softmax over the single kept score is the constant 1 and would pass no gradient
    to the scorer (nor to the morphology encoder before it): the gate would never learn. A top-1
    gate is therefore straight-through: its weight is ``1 + p - stop_gradient(p)``, with ``p`` the
    dense ``softmax(G(e))`` probability of the selected tailor, exactly 1 in the forward pass (the
    same actions as hard routing) and with the gradient of ``p`` in the backward pass (as the
    Switch Transformer's router, which scales its one expert by ``p``).

    :param in_dim: size of the conditioning embedding.
    :param n_units: number of tailors gated.
    :param k: number of tailors kept per sample.
    :param hidden_dim: hidden width of the scoring MLP ``G`` (0 = a single linear layer).
    :param name: which gate this is, for error messages (e.g. ``"morphology gate (top_k_morph)"``).
    """

    def __init__(self, in_dim: int, n_units: int, k: int, hidden_dim: int = 64, name: str = "gate"):
        super().__init__()
        if not 1 <= k <= n_units:
            raise ValueError(f"{name}: top-k must be in [1, {n_units}] (the number of tailors it gates), got {k}")
        self.n_units = n_units
        self.k = k
        if hidden_dim:
            self.score: nn.Module = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, n_units))
        else:
            self.score = nn.Linear(in_dim, n_units)

    def forward(self, embedding: th.Tensor) -> th.Tensor:
        """(B, in_dim) -> (B, n_units) gate weights."""
        return self.weights_and_probabilities(embedding)[0]

    def weights_and_probabilities(self, embedding: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Gate weights and the dense ``softmax(G(e))`` over every tailor (before TopK), which a
        load-balancing loss needs: unlike the weights, it gives every score a gradient."""
        scores = self.score(embedding)
        probabilities = th.softmax(scores, dim=-1)
        if self.k == self.n_units:
            return probabilities, probabilities
        top, index = scores.topk(self.k, dim=-1)
        if self.k == 1:
            # straight-through: the weight is exactly 1, its gradient that of the selected probability
            chosen = probabilities.gather(-1, index)
            weight = 1.0 + (chosen - chosen.detach())
            return th.zeros_like(scores).scatter(-1, index, weight), probabilities
        masked = th.full_like(scores, float("-inf")).scatter(-1, index, top)
        return th.softmax(masked, dim=-1), probabilities


def load_balancing_loss(weights: th.Tensor, probabilities: th.Tensor) -> th.Tensor:
    """Switch-Transformer load balance ``N * sum_i f_i P_i`` of one gate over a batch.

    ``f_i`` is the fraction of the batch's TopK selections that picked tailor ``i`` (no gradient),
    ``P_i`` the mean dense probability of tailor ``i``. It is 1 when use is uniform and up to ``N``
    when every sample picks the same tailors, and pushes the scores of over-used tailors down.

    :param weights: (B, N) TopK gate weights.
    :param probabilities: (B, N) dense softmax probabilities.
    """
    selected = (weights > 0).float()
    fraction = selected.sum(0) / selected.sum().clamp(min=1)
    return weights.shape[-1] * (fraction.detach() * probabilities.mean(0)).sum()


def masked_mean(tokens: th.Tensor, padding_mask: th.Tensor) -> th.Tensor:
    """Mean over real tokens: (B, L, D), (B, L) True = padded -> (B, D).

    ``where`` rather than multiplication, so a non-finite padded row cannot leak in as NaN.
    """
    real = ~padding_mask
    total = th.where(real[..., None], tokens, th.zeros((), dtype=tokens.dtype, device=tokens.device)).sum(1)
    return total / real.sum(1, keepdim=True).clamp(min=1).to(tokens.dtype)


class MorphologyEncoder(nn.Module):
    """Set encoder of a robot's static per-token context -> one morphology embedding.

    Tokens are embedded like the policy's tokens (linear + learnt position, so the torso is
    identifiable), mixed by a small dense pre-LN Transformer under the padding mask (limb features
    only become a *morphology* in relation to each other), then mean-pooled over real tokens and
    layer-normalised. ``n_layers=0`` gives a DeepSets encoder (embed, pool).

    :param context_dim: per-token context features.
    :param max_tokens: tokens per robot.
    :param embed_dim: width of the embedding.
    :param n_layers: Transformer layers.
    :param n_heads: attention heads.
    :param ff_dim: FFN width (default ``2 * embed_dim``).
    """

    def __init__(
        self,
        context_dim: int,
        max_tokens: int,
        embed_dim: int = 32,
        n_layers: int = 1,
        n_heads: int = 2,
        ff_dim: int | None = None,
    ):
        super().__init__()
        self.embed_dim = embed_dim
        self.embedding = TokenEmbedding(context_dim, embed_dim, max_tokens)
        self.encoder = TransformerEncoder(embed_dim, n_layers, n_heads, ff_dim or 2 * embed_dim)
        self.norm = nn.LayerNorm(embed_dim)

    def forward(self, context: th.Tensor, padding_mask: th.Tensor) -> th.Tensor:
        """
        :param context: (B, L, C) static per-token features.
        :param padding_mask: (B, L) boolean, True = padded.
        :return: (B, embed_dim).
        """
        context = th.where(padding_mask[..., None], th.zeros((), dtype=context.dtype, device=context.device), context)
        tokens = self.encoder(self.embedding(context), padding_mask)
        return self.norm(masked_mean(tokens, padding_mask))


class GateActivations(NamedTuple):
    """Per-sample gate weights."""

    morphology: th.Tensor  # (B, N_m)
    task: th.Tensor  # (B, N_t)

    def tailor_gates(self) -> th.Tensor:
        """(B, N_m + N_t), in the order tailors sit in every diverted layer."""
        return th.cat([self.morphology, self.task], dim=-1)


class DiversionRouter(nn.Module):
    """Morphology encoder + morphology-aware gate + task-aware gate.

    One router serves every diverted layer of the network (the same gate vector scales the tailors
    of every layer and projection type, as in DivControl/DivMorph).

    :param context_dim: per-token context features.
    :param max_tokens: tokens per robot.
    :param task_embedding_dim: size of the task (instruction) embedding.
    :param n_morph_tailors: ``N_m``.
    :param n_task_tailors: ``N_t``.
    :param top_k_morph: ``k`` of the morphology gate.
    :param top_k_task: ``k`` of the task gate.
    :param morph_embed_dim: width of the morphology embedding.
    :param morph_encoder_layers: Transformer layers of the morphology encoder.
    :param gate_hidden_dim: hidden width of both scoring MLPs.
    """

    def __init__(
        self,
        context_dim: int,
        max_tokens: int,
        task_embedding_dim: int,
        n_morph_tailors: int,
        n_task_tailors: int,
        top_k_morph: int,
        top_k_task: int,
        morph_embed_dim: int = 32,
        morph_encoder_layers: int = 1,
        gate_hidden_dim: int = 64,
    ):
        super().__init__()
        self.morphology_encoder = MorphologyEncoder(context_dim, max_tokens, morph_embed_dim, morph_encoder_layers)
        self.morphology_gate = TopKSoftGate(
            morph_embed_dim, n_morph_tailors, top_k_morph, gate_hidden_dim, name="morphology gate (top_k_morph, over n_morph_tailors)"
        )
        self.task_gate = TopKSoftGate(
            task_embedding_dim, n_task_tailors, top_k_task, gate_hidden_dim, name="task gate (top_k_task, over n_task_tailors)"
        )
        self._last: tuple[tuple, tuple[th.Tensor, ...], GateActivations] | None = None
        self._tensors: list[th.Tensor] | None = None  # the parameters, listed once (walking the modules costs ~40 us a step)

    def __setattr__(self, name: str, value: Any) -> None:
        super().__setattr__(name, value)
        if not name.startswith("_"):  # a part replaced: list the parameters again
            self.__dict__["_tensors"] = None

    def _apply(self, fn, recurse=True):  # .to(), .float(): tensors may be swapped
        self.__dict__["_tensors"] = None
        return super()._apply(fn, recurse)

    def forward(self, context: th.Tensor, padding_mask: th.Tensor, task_embedding: th.Tensor) -> GateActivations:
        """
        :param context: (B, L, C) static per-token features.
        :param padding_mask: (B, L) boolean, True = padded.
        :param task_embedding: (B, E) task instruction embedding.
        """
        if self.training or th.is_grad_enabled():
            self._last = None
            return self._route(context, padding_mask, task_embedding)
        # Rollouts feed the same robots and tasks step after step: reuse the last result while the
        # inputs and the parameters are unchanged.
        if self._tensors is None:
            self._tensors = list(self.parameters())
        key = tuple((p.data_ptr(), p._version) for p in self._tensors)
        inputs = (context, padding_mask, task_embedding)
        if (
            self._last is not None
            and self._last[0] == key
            and all(a.shape == b.shape and a.device == b.device and th.equal(a, b) for a, b in zip(self._last[1], inputs))
        ):
            return self._last[2]
        gates = self._route(context, padding_mask, task_embedding)
        self._last = (key, tuple(t.clone() for t in inputs), gates)
        return gates

    def _route(self, context: th.Tensor, padding_mask: th.Tensor, task_embedding: th.Tensor) -> GateActivations:
        gates, _ = self.route_with_probabilities(context, padding_mask, task_embedding)
        return gates

    def route_with_probabilities(
        self, context: th.Tensor, padding_mask: th.Tensor, task_embedding: th.Tensor
    ) -> tuple[GateActivations, GateActivations]:
        """The gates and, in the same layout, both gates' dense probabilities (see
        :meth:`TopKSoftGate.weights_and_probabilities`), for a load-balancing loss."""
        context = th.where(padding_mask[..., None], th.zeros((), dtype=context.dtype, device=context.device), context)
        morph_key = th.cat([context.flatten(1), padding_mask.to(context.dtype)], dim=-1)
        morph_rows, morph_index = _unique_rows(morph_key)
        task_rows, task_index = _unique_rows(task_embedding)
        morphology = self.morphology_encoder(context[morph_rows], padding_mask[morph_rows])
        morph_w, morph_p = self.morphology_gate.weights_and_probabilities(morphology)
        task_w, task_p = self.task_gate.weights_and_probabilities(task_embedding[task_rows])
        return (
            GateActivations(morph_w[morph_index], task_w[task_index]),
            GateActivations(morph_p[morph_index], task_p[task_index]),
        )


#: Below this batch size deduplication costs more than it saves.
_DEDUPLICATE_FROM = 16


def _unique_rows(key: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """Indices of one representative per distinct row of ``key`` (B, K), and each row's representative.

    A training batch holds few distinct robots and tasks, and their gates depend on nothing else,
    so the router runs once per distinct input and the result is gathered back (exactly the same
    values and gradients as running it per sample).
    """
    batch = key.shape[0]
    if batch < _DEDUPLICATE_FROM:
        index = th.arange(batch, device=key.device)
        return index, index
    key = key.detach()
    # ``th.unique(dim=0)`` compares rows one by one (hundreds of small ops per batch); a random
    # float64 projection turns each row into one number, which a 1-D unique groups in one sort.
    # Identical rows get identical numbers; the check below catches the (measure-zero) collision of
    # two different rows and falls back to the exact row-wise unique.
    _, inverse = th.unique((key.double() * _row_projection(key.shape[1], key.device)).sum(-1), return_inverse=True)
    first = th.full((int(inverse.max()) + 1,), batch, dtype=inverse.dtype, device=key.device)
    first = first.scatter_reduce(0, inverse, th.arange(batch, device=key.device), reduce="amin")
    if not th.equal(key[first][inverse], key):
        _, inverse = th.unique(key, dim=0, return_inverse=True)
        first = th.full((int(inverse.max()) + 1,), batch, dtype=inverse.dtype, device=key.device)
        first = first.scatter_reduce(0, inverse, th.arange(batch, device=key.device), reduce="amin")
    return first, inverse


def _row_projection(width: int, device: th.device) -> th.Tensor:
    """A fixed random float64 vector (its own generator: deduplication never shifts the global RNG)."""
    return th.randn(width, dtype=th.float64, generator=th.Generator().manual_seed(0)).to(device)
