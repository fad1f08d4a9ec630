"""Linear layers for the morphology-aware Transformer: dense, and factorized into rank-1 units.

A :class:`FactorizedLinear` stores a weight ``W = U diag(s) V^T`` taken from the SVD of an ordinary
random dense init, so that with every unit switched on it *is* that dense layer. Its ``r`` rank-1
units ``(u_i, s_i, v_i)`` are split, in singular-value order (largest first), into

* ``[0, N_G)``: learngenes, always on (gate 1),
* ``[N_G, N_G + N_m)``: morphology tailors, scaled by the morphology gate,
* ``[r - N_t, r)``: task tailors, scaled by the task gate,

following DivMorph (the paper indexes the units the same way). Gates are per sample, so one batch
may mix morphologies and tasks; the layer never builds a per-sample weight matrix (a rollout step
builds them once per robot batch in :mod:`sb3_divmorph.nn.fused`, where they pay).

Both layer kinds share the call signature ``layer(x, tailor_gates=None)`` so that networks can be
written once and built dense (MetaMorph) or factorized (DivMorph).
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple

import torch as th
from torch import nn
from torch.nn import functional as F

#: Initialiser applied in place to a freshly built dense ``nn.Linear``.
LinearInit = Callable[[nn.Linear], None]


class DenseLinear(nn.Linear):
    """``nn.Linear`` that accepts (and ignores) tailor gates, so it is interchangeable with
    :class:`FactorizedLinear` inside a network."""

    def forward(self, x: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:  # noqa: ARG002
        return F.linear(x, self.weight, self.bias)


@functools.lru_cache(maxsize=64)
def _upper_indices(size: int, device: th.device) -> th.Tensor:
    # made outside inference mode even when first asked for in a rollout: the cached index is read by
    # training passes too, which may not save an inference tensor for backward
    with th.inference_mode(False):
        return th.triu_indices(size, size, offset=1, device=device)


def cayley(skew_entries: th.Tensor, size: int) -> th.Tensor:
    """Cayley map ``(I + A)^-1 (I - A)`` of a skew-symmetric ``A``.

    ``A`` is assembled from its strict upper triangle, so it is skew-symmetric by construction and
    the result is orthogonal for any parameter value (no projection step needed).

    :param skew_entries: (size * (size - 1) / 2,) free entries of ``A`` above the diagonal, or
        (n, size * (size - 1) / 2) for ``n`` maps computed in one batched solve.
    :param size: ``r``.
    :return: (r, r) orthogonal matrix, or (n, r, r); the identity when the entries are zero.
    """
    upper = skew_entries.new_zeros(*skew_entries.shape[:-1], size, size)
    rows, cols = _upper_indices(size, skew_entries.device)
    upper[..., rows, cols] = skew_entries
    skew = upper - upper.transpose(-1, -2)
    eye = th.eye(size, dtype=skew.dtype, device=skew.device)
    return th.linalg.solve(eye + skew, eye - skew)


class _Factors(NamedTuple):
    """Everything a forward pass needs, computed once per parameter version."""

    U: th.Tensor  # (out, r)
    V: th.Tensor  # (in, r)
    #: dense weight of the always-on units: the learngenes, or every unit when nothing is gated;
    #: ``None`` for a gated layer on the low-rank path, which never reads it
    merged: th.Tensor | None  # (out, in)
    #: the tailors' columns of ``U`` and ``V`` and their singular values (merged path only): split
    #: once here, so a pass slices no parameter (each slice is an op forward and two backward)
    tailor_U: th.Tensor | None = None  # (out, N_m + N_t)
    tailor_V: th.Tensor | None = None  # (in, N_m + N_t)
    tailor_s: th.Tensor | None = None  # (N_m + N_t,)


class FactorizedLinear(nn.Module):
    """Linear layer ``y = x V diag(s * g) U^T + b`` made of rank-1 factor units.

    ``r = min(in_features, out_features)``, so one of ``U`` (out x r) and ``V`` (in x r) is square.
    That square factor is kept exactly orthogonal with a Cayley parametrization
    ``Q = Q0 cayley(A)`` (``Q0`` is the SVD factor, a buffer; ``A`` starts at zero). The other,
    tall factor and the singular values ``s`` are free parameters initialised from the SVD.

    ``g`` is 1 for learngenes and the per-sample tailor gates for tailors. Learngene gates are the
    same for every sample, so their rank-``N_G`` part is merged into one dense matrix shared by the
    batch; the tailor part runs as the per-sample low-rank path ``((x V_T) * s_T g) U_T^T``. When
    ``N_G`` is small that merge costs more than it saves, and the layer runs the whole low-rank path
    ``((x V) * s g) U^T`` instead (``path="auto"`` picks the cheaper one; both are exact).

    :param in_features: input size.
    :param out_features: output size.
    :param n_morph_tailors: number of morphology tailors ``N_m``.
    :param n_task_tailors: number of task tailors ``N_t``; learngenes are the remaining
        ``N_G = r - N_m - N_t`` units.
    :param orthogonal: keep the square factor orthogonal (Cayley); ``False`` trains it freely
        (ablation).
    :param weight: (out, in) dense init to factorize; default: ``nn.Linear``'s own init.
    :param bias: (out,) bias init, or ``None`` for no bias. Default: ``nn.Linear``'s own init.
    :param path: ``"auto"``, ``"merged"`` (learngenes merged, tailors low-rank) or ``"lowrank"``.
    :param gate_slots: ``(G_m, G_t)``, the sizes of the morphology and task gate vectors the layer
        is given, when they differ from its own tailor counts (a layer too small to hold one tailor
        per gate slot): its ``j``-th morphology tailor is then scaled by the sum of the gates of
        the ``j``-th of ``N_m`` contiguous groups of morphology slots (likewise for task tailors),
        so TopK still selects at most ``k`` of its tailors per gate. Default: one slot per tailor.
    :param adapter_rank: width of a zero-initialised low-rank adapter added to the weight,
        ``W + B A`` (LoRA: ``A`` random, ``B`` zero, so the layer starts as the factors alone); 0
        for none. Transfer's ``adapter`` recipe trains only the adapters; pruning keeps them as
        always-on units (:meth:`selected_units`).
    """

    # Buffers (register_buffer), declared for the type checker: Q0 when orthogonal; the gate pooling
    # when gate_slots differ from the tailor counts, else None.
    square_base: th.Tensor
    gate_pool: th.Tensor | None

    def __init__(
        self,
        in_features: int,
        out_features: int,
        n_morph_tailors: int = 0,
        n_task_tailors: int = 0,
        orthogonal: bool = True,
        weight: th.Tensor | None = None,
        bias: th.Tensor | None | bool = True,
        path: str = "auto",
        gate_slots: tuple[int, int] | None = None,
        adapter_rank: int = 0,
    ):
        super().__init__()
        rank = min(in_features, out_features)
        if adapter_rank < 0:
            raise ValueError(f"adapter_rank must be >= 0, got {adapter_rank}")
        n_tailors = n_morph_tailors + n_task_tailors
        if n_morph_tailors < 0 or n_task_tailors < 0 or n_tailors > rank:
            raise ValueError(
                f"A {out_features}x{in_features} layer has {rank} units; cannot hold "
                f"{n_morph_tailors} morphology + {n_task_tailors} task tailors."
            )
        slots = (n_morph_tailors, n_task_tailors) if gate_slots is None else tuple(int(g) for g in gate_slots)
        if (
            slots[0] < n_morph_tailors
            or slots[1] < n_task_tailors
            or (n_morph_tailors == 0) != (slots[0] == 0)
            or (n_task_tailors == 0) != (slots[1] == 0)
        ):
            raise ValueError(f"gate slots {slots} cannot drive {n_morph_tailors} morphology + {n_task_tailors} task tailors")
        self.gate_slots = slots
        if path not in ("auto", "merged", "lowrank"):
            raise ValueError(f"Unknown path {path!r}")
        if weight is None or bias is True:
            reference = nn.Linear(in_features, out_features)
            weight = reference.weight.detach() if weight is None else weight
            bias = reference.bias.detach() if bias is True else bias
        if tuple(weight.shape) != (out_features, in_features):
            raise ValueError(f"weight has shape {tuple(weight.shape)}, expected {(out_features, in_features)}")

        self.in_features = in_features
        self.out_features = out_features
        self.rank = rank
        self.n_morph_tailors = n_morph_tailors
        self.n_task_tailors = n_task_tailors
        self.n_tailors = n_tailors
        self.n_learngenes = rank - n_tailors
        self.orthogonal = orthogonal
        self.square_side = "U" if out_features <= in_features else "V"

        # float64 SVD: the float32 factors then reproduce the init to ~1e-7 and the square factor
        # starts orthogonal to float32 precision, which the Cayley map then preserves.
        u, s, vh = th.linalg.svd(weight.detach().double(), full_matrices=False)
        v = vh.transpose(0, 1)
        square, tall = (u, v) if self.square_side == "U" else (v, u)
        dtype = weight.dtype if weight.is_floating_point() else th.float32
        self.singular_values = nn.Parameter(s.to(dtype))
        self.tall = nn.Parameter(tall.to(dtype).contiguous())
        if orthogonal:
            self.register_buffer("square_base", square.to(dtype).contiguous())
            self.square_skew = nn.Parameter(th.zeros(rank * (rank - 1) // 2, dtype=dtype))
        else:
            self.square = nn.Parameter(square.to(dtype).contiguous())
        self.bias = None if bias is None or bias is False else nn.Parameter(bias.detach().to(dtype).clone())
        self.adapter_rank = int(adapter_rank)
        if adapter_rank:
            # LoRA's start: a random down-projection of nn.Linear's scale and a zero up-projection
            bound = 1.0 / math.sqrt(in_features)
            self.adapter_down = nn.Parameter(th.empty(adapter_rank, in_features, dtype=dtype).uniform_(-bound, bound))
            self.adapter_up = nn.Parameter(th.zeros(out_features, adapter_rank, dtype=dtype))

        # Per-row multiply-adds of both paths; the merged one also builds an (out x in) matrix
        # once per batch, which is negligible for training minibatches and cached in rollouts.
        merged_cost = in_features * out_features + n_tailors * (in_features + out_features)
        lowrank_cost = rank * (in_features + out_features)
        self.path = path if path != "auto" else ("merged" if merged_cost <= lowrank_cost else "lowrank")
        self._cache: tuple[tuple, _Factors] | None = None
        #: the square factor of the current forward pass, when :func:`batched_square_factors` computed it
        self._shared_square: th.Tensor | None = None
        if slots != (n_morph_tailors, n_task_tailors):
            self.register_buffer(
                "gate_pool", th.block_diag(slot_pooling(slots[0], n_morph_tailors), slot_pooling(slots[1], n_task_tailors))
            )
        else:
            self.gate_pool = None

    @property
    def n_gates(self) -> int:
        """Width of the gate vector the layer takes (``G_m + G_t``)."""
        return sum(self.gate_slots) if self.n_tailors else 0

    def local_gates(self, tailor_gates: th.Tensor) -> th.Tensor:
        """(..., G_m + G_t) gate slots -> (..., N_m + N_t) gates of this layer's own tailors."""
        if tailor_gates.shape[-1] != self.n_gates:
            raise ValueError(f"expected {self.n_gates} tailor gates, got {tailor_gates.shape[-1]}")
        return tailor_gates if self.gate_pool is None else tailor_gates @ self.gate_pool

    # ------------------------------------------------------------------------------------------
    @property
    def unit_slices(self) -> dict[str, slice]:
        """Singular indices of each unit group."""
        g, m = self.n_learngenes, self.n_morph_tailors
        return {
            "learngene": slice(0, g),
            "morphology": slice(g, g + m),
            "task": slice(g + m, self.rank),
        }

    def square_factor(self) -> th.Tensor:
        """The square factor (``U`` or ``V`` as :attr:`square_side` says), orthogonal if requested."""
        if self._shared_square is not None:
            return self._shared_square
        if self.orthogonal:
            return self.square_base @ cayley(self.square_skew, self.rank)
        return self.square

    @th.no_grad()
    def rebase_square_factor(self) -> None:
        """Fold the current rotation into the base: ``Q0 <- Q0 cayley(A)``, ``A <- 0``.

        The layer computes exactly the same function afterwards. What changes is what a skew entry
        ``A_ij`` does from here on: ``cayley(A)`` mixes units ``i`` and ``j`` only through the
        entries it has, so with ``A`` restarted at zero, a unit whose row and column of ``A`` stay
        zero keeps its column of ``Q`` bit for bit (transfer freezes unselected tailors this way).
        A no-op without orthogonality (the square factor is then a free parameter).
        """
        if not self.orthogonal:
            return
        self.square_base.copy_(self.square_base @ cayley(self.square_skew, self.rank))
        self.square_skew.zero_()
        self._cache = None

    def orthogonality_error(self) -> float:
        """``max |Q^T Q - I|`` of the square factor."""
        with th.no_grad():
            q = self.square_factor().double()
            return (q.T @ q - th.eye(self.rank, dtype=q.dtype, device=q.device)).abs().max().item()

    def _compute_factors(self) -> _Factors:
        square = self.square_factor()
        U, V = (square, self.tall) if self.square_side == "U" else (self.tall, square)
        if self.n_tailors and self.path == "lowrank":
            return _Factors(U, V, None)  # building it would cost a matmul (and its backward) per step
        if self.n_tailors == 0:
            return _Factors(U, V, (U * self.singular_values) @ V.T)
        sizes = [self.n_learngenes, self.n_tailors]
        (learngene_U, tailor_U), (learngene_V, tailor_V) = U.split(sizes, dim=1), V.split(sizes, dim=1)
        learngene_s, tailor_s = self.singular_values.split(sizes)
        return _Factors(U, V, (learngene_U * learngene_s) @ learngene_V.T, tailor_U, tailor_V, tailor_s)

    def factors(self) -> _Factors:
        """``U``, ``V`` and the merged always-on weight.

        In eval mode without autograd (SB3 rollouts, ``predict``) the result is cached until a
        parameter changes, so the Cayley solve is not repeated at every environment step.
        """
        if self.training or th.is_grad_enabled():
            self._cache = None
            return self._compute_factors()
        tensors = [self.singular_values, self.tall, *((self.square_base, self.square_skew) if self.orthogonal else (self.square,))]
        key = tuple((t.data_ptr(), t._version, t.device) for t in tensors)
        if self._cache is None or self._cache[0] != key:
            self._cache = (key, self._compute_factors())
        return self._cache[1]

    def unit_scales(self, tailor_gates: th.Tensor | None) -> th.Tensor:
        """Per-sample effective singular values ``s * g``: (r,) without gates, else (B, r).

        :param tailor_gates: (B, G_m + G_t) gate slots (see ``gate_slots``), or ``None``.
        """
        s = self.singular_values
        if tailor_gates is None or self.n_tailors == 0:
            return s
        # learngenes' gate is 1: pad the tailor gates in front (one op, no slicing of s)
        return s * F.pad(self.local_gates(tailor_gates), (self.n_learngenes, 0), value=1.0)

    def dense_weight(self, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """The weight matrix for one gate vector (analysis and export; not used in forward).

        :param tailor_gates: (N_m + N_t,) gates of one sample, or ``None`` for all units on.
        """
        U, V = self.factors()[:2]
        scales = self.unit_scales(None if tailor_gates is None else tailor_gates.reshape(1, -1)).reshape(-1)
        weight = (U * scales) @ V.T
        return weight + self.adapter_up @ self.adapter_down if self.adapter_rank else weight

    def selected_units(self, tailor_gates: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Compact factors for one gate vector: learngenes plus the tailors with a non-zero gate.

        Tailors the TopK gates did not select contribute exactly nothing, so dropping them gives
        the same layer with fewer units (DivMorph's deployment pruning):
        ``W = U_sel diag(s_sel) V_sel^T``. An adapter's ``B A`` is appended as ``adapter_rank``
        further units (columns of ``B`` and of ``A^T``, singular value 1).

        :param tailor_gates: (N_m + N_t,) gates of one sample, or ``None`` for every unit.
        :return: ``U_sel`` (out, k), ``s_sel`` (k,), ``V_sel`` (in, k), detached.
        """
        with th.no_grad():
            U, V = self.factors()[:2]
            scales = self.unit_scales(None if tailor_gates is None else tailor_gates.reshape(1, -1)).reshape(-1)
            keep = th.ones(self.rank, dtype=th.bool, device=scales.device)
            if tailor_gates is not None and self.n_tailors:
                keep[self.n_learngenes :] = self.local_gates(tailor_gates.reshape(1, -1)).reshape(-1) != 0
            U, scales, V = U[:, keep], scales[keep], V[:, keep]
            if self.adapter_rank:
                U = th.cat([U, self.adapter_up], dim=1)
                scales = th.cat([scales, th.ones(self.adapter_rank, dtype=scales.dtype, device=scales.device)])
                V = th.cat([V, self.adapter_down.T], dim=1)
            return U.clone(), scales.clone(), V.clone()

    def forward(self, x: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
        """
        :param x: (B, ..., in_features).
        :param tailor_gates: (B, G_m + G_t) per-sample gates (morphology then task), or ``None``
            to switch every unit on (the layer is then the dense init it was built from).
        :return: (B, ..., out_features).
        """
        out = self._factor_forward(x, tailor_gates)
        if self.adapter_rank:
            out = out + F.linear(F.linear(x, self.adapter_down), self.adapter_up)
        return out

    def _factor_forward(self, x: th.Tensor, tailor_gates: th.Tensor | None) -> th.Tensor:
        f = self.factors()
        if tailor_gates is None or self.n_tailors == 0:
            if self.n_tailors == 0:
                return F.linear(x, f.merged, self.bias)
            return F.linear(x, (f.U * self.singular_values) @ f.V.T, self.bias)
        # Work on (rows, features) so every product is one BLAS call and bias / partial sums are
        # fused into addmm; per-sample scales broadcast over each sample's rows.
        batch = tailor_gates.shape[0]
        rows = x.reshape(-1, self.in_features)
        if self.path == "merged":
            scales = (f.tailor_s * self.local_gates(tailor_gates))[:, None, :]
            hidden = ((rows @ f.tailor_V).view(batch, -1, self.n_tailors) * scales).view(-1, self.n_tailors)
            out = th.addmm(F.linear(rows, f.merged, self.bias), hidden, f.tailor_U.T)
        else:
            scales = self.unit_scales(tailor_gates)[:, None, :]
            hidden = ((rows @ f.V).view(batch, -1, self.rank) * scales).view(-1, self.rank)
            out = F.linear(hidden, f.U, self.bias)
        return out.view(*x.shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        return (
            f"in_features={self.in_features}, out_features={self.out_features}, "
            f"learngenes={self.n_learngenes}, morph_tailors={self.n_morph_tailors}, "
            f"task_tailors={self.n_task_tailors}, orthogonal={self.orthogonal}, "
            f"square={self.square_side}, path={self.path}"
            + (f", gate_slots={self.gate_slots}" if self.gate_pool is not None else "")
            + (f", adapter_rank={self.adapter_rank}" if self.adapter_rank else "")
        )


@contextlib.contextmanager
def batched_square_factors(module: nn.Module) -> Iterator[None]:
    """Compute the square factors of every orthogonal :class:`FactorizedLinear` in ``module`` with
    one batched Cayley solve per rank, for the forward passes inside the ``with`` block.

    A DivMorph actor holds a dozen or more such layers; a training step would otherwise solve (and
    back-propagate through) each of them separately, a handful of small LAPACK calls apiece. The
    batched solve gives the same factors and gradients up to float rounding (a unit whose skew row
    and column are zero keeps its column exactly, so transfer's freezing stays exact). Outside
    training and autograd (rollouts) nothing is done: each layer then caches its own factors.

    :param module: any module; layers without orthogonal square factors are left alone.
    """
    if not (module.training or th.is_grad_enabled()):
        yield  # a rollout step: each layer's cached factors serve, and no module walk on this hot path
        return
    layers = [m for m in module.modules() if isinstance(m, FactorizedLinear) and m.orthogonal]
    if not layers or any(m._shared_square is not None for m in layers):
        yield  # nothing to share, or an enclosing block already shares
        return
    groups: dict[tuple, list[FactorizedLinear]] = {}
    for layer in layers:
        groups.setdefault((layer.rank, layer.square_skew.dtype, layer.square_skew.device), []).append(layer)
    try:
        for (rank, _, _), group in groups.items():
            rotations = cayley(th.stack([layer.square_skew for layer in group]), rank)
            squares = th.stack([layer.square_base for layer in group]) @ rotations
            for layer, square in zip(group, squares.unbind(0)):
                layer._shared_square = square
        yield
    finally:
        for layer in layers:
            layer._shared_square = None


def slot_pooling(n_slots: int, n_tailors: int) -> th.Tensor:
    """(n_slots, n_tailors) 0/1 matrix: slot ``s`` feeds tailor ``floor(s * n_tailors / n_slots)``
    (contiguous, near-equal groups; the identity when the counts are equal)."""
    pool = th.zeros(n_slots, n_tailors)
    if n_tailors:
        pool[th.arange(n_slots), th.arange(n_slots) * n_tailors // n_slots] = 1.0
    return pool


@dataclass(frozen=True)
class Factorization:
    """How a network's projections are factorized (DivMorph) or left dense (``None``).

    :param n_morph_tailors: morphology tailors per diverted layer.
    :param n_task_tailors: task tailors per diverted layer.
    :param orthogonal: Cayley-orthogonal square factors.
    :param divert: gate the tailors; ``False`` factorizes without diversion (every unit is a
        learngene), the ablation that keeps the parametrization but drops the routing.
    :param n_learngenes: ``None``: every diverted layer holds exactly ``N_m + N_t`` tailors (one
        per gate slot) and its remaining units are learngenes, so its rank must exceed
        ``N_m + N_t``. An int ``N_G``: tailor counts are sized per layer instead: a diverted layer of
        rank ``r`` keeps ``N_G`` learngenes and splits the other ``r - N_G`` units into morphology
        and task tailors in the ratio ``N_m : N_t`` (at most one per gate slot; layers with fewer
        tailors than slots pool the slots, see ``FactorizedLinear``'s ``gate_slots``). A layer of
        rank below ``N_G + 2`` (e.g. the 3-input goal encoder) keeps ``r - 2`` learngenes, at least
        one. Few learngenes and a small TopK make the deployed actor small.
    :param adapter_rank: a zero-initialised low-rank adapter of this width on every factorized
        layer (``FactorizedLinear``'s ``adapter_rank``); 0 for none.
    """

    n_morph_tailors: int
    n_task_tailors: int
    orthogonal: bool = True
    divert: bool = True
    n_learngenes: int | None = None
    adapter_rank: int = 0

    @property
    def n_tailors(self) -> int:
        return self.n_morph_tailors + self.n_task_tailors

    def layer_tailors(self, rank: int) -> tuple[int, int] | None:
        """``(N_m, N_t)`` of a diverted layer of this rank, or ``None`` if it cannot hold them."""
        if self.n_learngenes is None:
            return (self.n_morph_tailors, self.n_task_tailors) if rank > self.n_tailors else None
        kinds = int(self.n_morph_tailors > 0) + int(self.n_task_tailors > 0)
        if self.n_tailors == 0 or rank < 1 + kinds:
            return None
        # a layer too small for N_G learngenes plus one tailor per kind keeps fewer learngenes (>= 1)
        free = rank - min(self.n_learngenes, rank - kinds)
        morph = min(self.n_morph_tailors, max(int(self.n_morph_tailors > 0), round(free * self.n_morph_tailors / self.n_tailors)))
        task = min(self.n_task_tailors, free - morph)
        if self.n_task_tailors > 0 and task < 1:
            morph, task = morph - 1, 1
        return morph, task


class LayerDiversionError(ValueError):
    """A layer asked to be diverted cannot hold the requested tailors."""


class LinearBuilder:
    """Builds every projection of a network the same way: dense, or factorized from the dense init.

    Every layer built with ``divert=True`` (the default) is diverted, or the build fails with a
    :class:`LayerDiversionError` naming the layer, its rank and the requested counts: a diversion
    is never switched off silently. Layers that are never diverted (the 2-output action head, the
    value head) say so with ``divert=False`` and are factorized with every unit a learngene.

    :param factorization: ``None`` for dense layers.
    """

    def __init__(self, factorization: Factorization | None = None):
        self.factorization = factorization

    @property
    def tailor_gates_size(self) -> int:
        f = self.factorization
        return 0 if f is None or not f.divert else f.n_tailors

    def __call__(
        self, in_features: int, out_features: int, init: LinearInit | None = None, name: str = "layer", divert: bool = True
    ) -> nn.Module:
        """
        :param in_features: input size.
        :param out_features: output size.
        :param init: in-place initialiser of the dense init (default: ``nn.Linear``'s).
        :param name: the layer's name in errors (e.g. ``"transformer.0.ff_in"``).
        :param divert: whether the layer is meant to carry tailors (when the factorization diverts).
        """
        dense = DenseLinear(in_features, out_features)
        if init is not None:
            init(dense)
        f = self.factorization
        if f is None:
            return dense
        counts = (0, 0)
        if f.divert and divert and f.n_tailors:
            rank = min(in_features, out_features)
            fitted = f.layer_tailors(rank)
            if fitted is None:
                need = f"rank > {f.n_tailors}" if f.n_learngenes is None else "rank >= 3 (a learngene and a tailor of each kind)"
                raise LayerDiversionError(
                    f"cannot divert layer {name!r} ({out_features}x{in_features}, rank {rank}): "
                    f"{f.n_morph_tailors} morphology + {f.n_task_tailors} task tailors"
                    + ("" if f.n_learngenes is None else f" with {f.n_learngenes} learngenes")
                    + f" need {need}. Use fewer tailors, set n_learngenes to size tailors per layer, or do not divert this part."
                )
            counts = fitted
        return FactorizedLinear(
            in_features,
            out_features,
            n_morph_tailors=counts[0],
            n_task_tailors=counts[1],
            orthogonal=f.orthogonal,
            weight=dense.weight.detach(),
            bias=dense.bias.detach(),
            gate_slots=(f.n_morph_tailors, f.n_task_tailors) if any(counts) else None,
            adapter_rank=f.adapter_rank,
        )


def is_diverted(module: nn.Module) -> bool:
    """Whether a layer takes tailor gates."""
    return isinstance(module, FactorizedLinear) and module.n_tailors > 0


def project_many(layers: list[nn.Module], x: th.Tensor, tailor_gates: th.Tensor | None = None) -> list[th.Tensor]:
    """Apply several projections of the same input (e.g. q, k, v) with as few BLAS calls as possible.

    Dense layers become one matmul over their stacked weights (what ``nn.MultiheadAttention`` does
    with its in-projection). Gated factorized layers on the merged path share one matmul for their
    stacked learngene weights and one for their stacked tailor down-projections; only the tailor
    up-projections stay separate. Anything else falls back to one call per layer. The results are
    identical to ``[layer(x, tailor_gates) for layer in layers]`` up to float rounding.

    :param layers: projections with the same ``in_features``.
    :param x: (B, ..., in_features).
    :param tailor_gates: (B, N_m + N_t) or ``None``.
    :return: one (B, ..., out_features) tensor per layer.
    """
    if all(type(layer) is DenseLinear for layer in layers):
        weight = th.cat([layer.weight for layer in layers])
        bias = None if any(layer.bias is None for layer in layers) else th.cat([layer.bias for layer in layers])
        if bias is None and any(layer.bias is not None for layer in layers):
            return [layer(x, tailor_gates) for layer in layers]
        return list(F.linear(x, weight, bias).split([layer.out_features for layer in layers], dim=-1))
    gated = tailor_gates is not None and all(
        isinstance(layer, FactorizedLinear) and layer.n_tailors > 0 and layer.path == "merged" and layer.bias is not None
        for layer in layers
    )
    if not gated:
        return [layer(x, tailor_gates) for layer in layers]
    factors = [layer.factors() for layer in layers]
    batch = tailor_gates.shape[0]
    rows = x.reshape(-1, x.shape[-1])
    learngene_out = F.linear(rows, th.cat([f.merged for f in factors]), th.cat([layer.bias for layer in layers])).split(
        [layer.out_features for layer in layers], dim=-1
    )
    down = th.cat([f.tailor_V for f in factors], dim=1)
    scales = th.cat([f.tailor_s * layer.local_gates(tailor_gates) for f, layer in zip(factors, layers)], dim=-1)
    hidden = ((rows @ down).view(batch, -1, scales.shape[-1]) * scales[:, None, :]).view(-1, scales.shape[-1])
    tailor_hidden = hidden.split([layer.n_tailors for layer in layers], dim=1)
    outs = [th.addmm(out, part, f.tailor_U.T) for out, part, f in zip(learngene_out, tailor_hidden, factors)]
    # an adapter adds its own term, as in FactorizedLinear.forward (exactly nothing while B = 0)
    outs = [
        out + F.linear(F.linear(rows, layer.adapter_down), layer.adapter_up) if layer.adapter_rank else out
        for out, layer in zip(outs, layers)
    ]
    return [out.view(*x.shape[:-1], layer.out_features) for out, layer in zip(outs, layers)]


def project_concat(layers: list[nn.Module], x: th.Tensor, tailor_gates: th.Tensor | None = None) -> th.Tensor:
    """:func:`project_many`'s outputs side by side, (B, ..., sum of out_features): dense layers give
    their one matmul's output as it is, without splitting it and joining the parts again."""
    if all(type(layer) is DenseLinear and layer.bias is not None for layer in layers):
        return F.linear(x, th.cat([layer.weight for layer in layers]), th.cat([layer.bias for layer in layers]))
    return th.cat(project_many(layers, x, tailor_gates), dim=-1)
