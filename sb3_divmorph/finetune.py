"""Transfer of a distilled DivMorph student to a novel task: fixed gates, per-unit learning rates.

DivMorph adapts to a new task by keeping its morphology and task gates fixed and training the
tailors those gates select, with small adjustments to the learngenes. Units of a
:class:`~sb3_divmorph.layers.FactorizedLinear` share tensors (a unit is a column of ``U`` and ``V``
and an entry of ``s``), so they cannot sit in separate optimiser parameter groups, and scaling
their gradients would be undone by Adam's normalisation. :class:`UnitLearningRates` therefore
scales each element's *update*: it snapshots the parameters before every optimiser step and
afterwards moves each element only ``scale`` of the way, which for Adam (or SGD) is exactly a
per-element learning rate of ``scale x lr``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import torch as th
from torch import nn

from sb3_divmorph.layers import FactorizedLinear, _upper_indices


@dataclass(frozen=True)
class UnitSelection:
    """Which tailors the gates select for the robots and task of a transfer.

    :param morphology: (N_m,) bool, tailor selected for at least one robot.
    :param task: (N_t,) bool, tailor selected for the task.
    """

    morphology: np.ndarray
    task: np.ndarray

    @property
    def tailors(self) -> np.ndarray:
        """(N_m + N_t,) in the order tailors sit in every diverted layer."""
        return np.concatenate([self.morphology, self.task])

    @classmethod
    def from_gates(cls, morphology_gates: np.ndarray, task_gates: np.ndarray) -> UnitSelection:
        """Tailors with a non-zero gate for any sample: (B, N_m), (B, N_t) -> selection."""
        return cls(np.asarray(morphology_gates != 0).any(0), np.asarray(task_gates != 0).any(0))


def unit_scales(layer: FactorizedLinear, selection: UnitSelection, learngene_scale: float) -> th.Tensor:
    """(r,) learning-rate scale per unit: ``learngene_scale`` for learngenes, 1 for selected
    tailors, 0 for tailors the gates never select (their update would have no effect anyway)."""
    scales = th.full((layer.rank,), float(learngene_scale))
    if layer.n_tailors:
        scales[layer.n_learngenes :] = th.as_tensor(selection.tailors, dtype=th.float32)
    return scales


def factor_parameter_scales(layer: FactorizedLinear, unit: th.Tensor, bias_scale: float) -> dict[nn.Parameter, th.Tensor]:
    """Per-element scales of a factorized layer's parameters from its per-unit scales.

    A Cayley skew entry ``A_ij`` rotates units ``i`` and ``j`` into each other, so it moves at the
    rate of the slower of the two.
    """
    scales: dict[nn.Parameter, th.Tensor] = {
        layer.singular_values: unit.clone(),
        layer.tall: unit.expand_as(layer.tall).clone(),
    }
    if layer.orthogonal:
        rows, cols = _upper_indices(layer.rank, th.device("cpu"))
        scales[layer.square_skew] = th.minimum(unit[rows], unit[cols])
    else:
        scales[layer.square] = unit.expand_as(layer.square).clone()
    if layer.bias is not None:
        scales[layer.bias] = th.full_like(layer.bias, bias_scale, device="cpu")
    return scales


class UnitLearningRates:
    """Per-element learning-rate scales applied around an optimiser's ``step``.

    Parameters not listed move at the optimiser's full rate. A scale of 0 freezes an element
    exactly. The hooks live on the optimiser object: install them again after loading a model.

    :param optimizer: the optimiser (e.g. ``model.policy.optimizer``).
    :param scales: ``{parameter: scale tensor broadcastable to it}``.
    """

    def __init__(self, optimizer: th.optim.Optimizer, scales: Mapping[nn.Parameter, th.Tensor]):
        self.optimizer = optimizer
        self.scales = {p: s.to(p.device, p.dtype) for p, s in scales.items() if not th.all(s == 1)}
        self._before: dict[nn.Parameter, th.Tensor] = {}
        self._handles = [
            optimizer.register_step_pre_hook(self._snapshot),
            optimizer.register_step_post_hook(self._rescale),
        ]

    def _snapshot(self, *_args) -> None:
        self._before = {p: p.detach().clone() for p in self.scales}

    @th.no_grad()
    def _rescale(self, *_args) -> None:
        for p, scale in self.scales.items():
            before = self._before[p]
            p.copy_(before + scale * (p - before))
        self._before = {}

    def remove(self) -> None:
        """Uninstall the hooks (the optimiser then updates every element at its full rate)."""
        for handle in self._handles:
            handle.remove()


def freeze(modules: Iterable[nn.Module]) -> int:
    """``requires_grad = False`` on every parameter of ``modules``; returns how many elements."""
    count = 0
    for module in modules:
        for p in module.parameters():
            p.requires_grad_(False)
            count += p.numel()
    return count


def actor_modules(policy: nn.Module) -> list[nn.Module]:
    """The modules a DivMorph policy's actions depend on (router excluded)."""
    extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
    return [extractor, policy.mlp_extractor.policy_net, policy.action_net]


def prepare_transfer(
    policy: nn.Module, selection: UnitSelection, learngene_scale: float = 0.1
) -> UnitLearningRates:
    """Set a DivMorph policy up for DivMorph transfer, in place.

    * the router (morphology encoder and both gates) is frozen, so the gates stay fixed;
    * in every factorized actor layer, selected tailors train at the full learning rate, the
      learngenes at ``learngene_scale`` of it, unselected tailors not at all;
    * the actor's other parameters (token embedding, layer norms, biases, exteroception
      encoders), which carry shared knowledge like the learngenes, train at ``learngene_scale``;
    * the critic (never distilled) trains at the full rate.

    :param policy: a :class:`~sb3_divmorph.policies.DivMorphPolicy` (its optimiser must exist).
    :param selection: the tailors the fixed gates select (:meth:`UnitSelection.from_gates`).
    :param learngene_scale: learning-rate ratio of the shared knowledge to the selected tailors.
    :return: the installed :class:`UnitLearningRates` (keep it, or call ``remove``).
    """
    if not hasattr(policy, "router"):
        raise TypeError(f"transfer with fixed gates needs a DivMorphPolicy, got {type(policy).__name__}")
    if not 0 <= learngene_scale <= 1:
        raise ValueError(f"learngene_scale must be in [0, 1], got {learngene_scale}")
    freeze([policy.router])
    scales: dict[nn.Parameter, th.Tensor] = {}
    for module in actor_modules(policy):
        for layer in module.modules():
            if isinstance(layer, FactorizedLinear):
                scales.update(factor_parameter_scales(layer, unit_scales(layer, selection, learngene_scale), learngene_scale))
        for p in module.parameters():
            if p.requires_grad and p not in scales:
                scales[p] = th.full((), float(learngene_scale))
    if isinstance(getattr(policy, "log_std", None), nn.Parameter):
        scales[policy.log_std] = th.full((), float(learngene_scale))
    return UnitLearningRates(policy.optimizer, scales)
