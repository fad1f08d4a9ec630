"""Transfer of a distilled DivMorph student to a novel task: fixed gates, per-unit learning rates.

DivMorph adapts to a new task by keeping its morphology and task gates fixed and training the
tailors those gates select, with small adjustments to the learngenes. Units of a
:class:`~sb3_divmorph.nn.layers.FactorizedLinear` share tensors (a unit is a column of ``U`` and ``V``
and an entry of ``s``), so they cannot sit in separate optimiser parameter groups, and scaling
their gradients would be undone by Adam's normalisation. :class:`UnitLearningRates` therefore
scales each element's *update*: it snapshots the parameters before every optimiser step and
afterwards moves each element only ``scale`` of the way, which for Adam (or SGD) is exactly a
per-element learning rate of ``scale x lr``.

Two details make that exact in practice:

* the Cayley skew ``A`` of a square factor mixes every unit with every other once ``A != 0``, so
  :func:`prepare_transfer` first folds the distilled rotation into the base
  (:meth:`~sb3_divmorph.nn.layers.FactorizedLinear.rebase_square_factor`); restarted at zero with its
  rows and columns of unselected units frozen, ``A`` then never touches those units;
* Adam's ``eps`` (1e-5 in SB3) is larger than the gradients of a distilled student's tailors
  (~1e-6), so Adam would not normalise them and the effective ratio would depend on gradient sizes;
  transfer runs Adam with ``adam_eps`` (1e-10 by default) and :class:`UnitLearningRates` measures
  the ratio actually applied (:meth:`UnitLearningRates.measured_ratio`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from sb3_divmorph.nn.layers import FactorizedLinear, _upper_indices


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


def factor_parameter_scales(
    layer: FactorizedLinear, unit: th.Tensor, bias_scale: float, rotation_scale: float = 1.0
) -> dict[nn.Parameter, th.Tensor]:
    """Per-element scales of a factorized layer's parameters from its per-unit scales.

    A Cayley skew entry ``A_ij`` rotates units ``i`` and ``j`` into each other, so it moves at the
    rate of the slower of the two, times ``rotation_scale``: Adam moves every entry by about the
    rate at once, and each rotates two whole singular directions weighted by their singular values,
    so at one rate for all the rotations move the function far more than the other factors do.
    A free square factor (a student without orthogonality) moves its units' columns at their rates
    times ``rotation_scale`` too, so that ``rotation_scale=0`` fixes every square factor alike.
    """
    scales: dict[nn.Parameter, th.Tensor] = {
        layer.singular_values: unit.clone(),
        layer.tall: unit.expand_as(layer.tall).clone(),
    }
    if layer.orthogonal:
        rows, cols = _upper_indices(layer.rank, th.device("cpu"))
        scales[layer.square_skew] = th.minimum(unit[rows], unit[cols]) * float(rotation_scale)
    else:
        scales[layer.square] = unit.expand_as(layer.square) * float(rotation_scale)
    if layer.bias is not None:
        scales[layer.bias] = th.full_like(layer.bias, bias_scale, device="cpu")
    return scales


class UnitLearningRates:
    """Per-element learning-rate scales applied around an optimiser's ``step``.

    Parameters not listed move at the optimiser's full rate. A scale of 0 freezes an element
    exactly. The hooks live on the optimiser object: install them again after loading a model.

    With ``groups``, every step also accumulates the mean absolute update of each named group of
    elements, so the learning-rate ratio actually applied can be read back
    (:meth:`mean_updates`, :meth:`measured_ratio`).

    :param optimizer: the optimiser (e.g. ``model.policy.optimizer``).
    :param scales: ``{parameter: scale tensor broadcastable to it}``.
    :param groups: ``{group name: {parameter: bool mask of its elements}}`` to measure.
    """

    def __init__(
        self,
        optimizer: th.optim.Optimizer,
        scales: Mapping[nn.Parameter, th.Tensor],
        groups: Mapping[str, Mapping[nn.Parameter, th.Tensor]] | None = None,
    ):
        self.optimizer = optimizer
        self.scales = {p: s.to(p.device, p.dtype) for p, s in scales.items() if not th.all(s == 1)}
        self.groups = {
            name: {p: m.to(p.device).expand_as(p) for p, m in masks.items() if m.any()} for name, masks in (groups or {}).items()
        }
        self._moved = {name: 0.0 for name in self.groups}
        self._counted = {name: 0 for name in self.groups}
        watched = set(self.scales) | {p for masks in self.groups.values() for p in masks}
        self._before: dict[nn.Parameter, th.Tensor] = {}
        self._watched = list(watched)
        self._handles = [
            optimizer.register_step_pre_hook(self._snapshot),
            optimizer.register_step_post_hook(self._rescale),
        ]

    def _snapshot(self, *_args) -> None:
        self._before = {p: p.detach().clone() for p in self._watched}

    @th.no_grad()
    def _rescale(self, *_args) -> None:
        for p, scale in self.scales.items():
            before = self._before[p]
            p.copy_(before + scale * (p - before))
        for name, masks in self.groups.items():
            for p, mask in masks.items():
                self._moved[name] += float((p - self._before[p]).abs()[mask].sum())
                self._counted[name] += int(mask.sum())
        self._before = {}

    def mean_updates(self, reset: bool = False) -> dict[str, float]:
        """Mean absolute update per element and optimiser step of each group since the last reset."""
        means = {name: self._moved[name] / self._counted[name] if self._counted[name] else float("nan") for name in self.groups}
        if reset:
            self._moved = {name: 0.0 for name in self.groups}
            self._counted = {name: 0 for name in self.groups}
        return means

    def measured_ratio(self, numerator: str = "learngene", denominator: str = "selected_tailor", reset: bool = False) -> float:
        """Ratio of two groups' mean absolute updates (e.g. learngenes / selected tailors)."""
        means = self.mean_updates(reset)
        return means[numerator] / means[denominator] if means[denominator] else float("nan")

    def remove(self) -> None:
        """Uninstall the hooks (the optimiser then updates every element at its full rate)."""
        for handle in self._handles:
            handle.remove()


class FrozenRunningMeanStd(RunningMeanStd):
    """Running statistics that no longer learn: ``update`` and ``combine`` leave them as they are.

    A ``VecNormalize`` holding these as its observation statistics normalises observations with
    the statistics it was given while its reward statistics (a plain ``RunningMeanStd``) go on
    learning. It pickles with the normaliser, so checkpoints and the saved ``vecnormalize.pkl``
    keep the statistics frozen when loaded again.

    :param statistics: the statistics to freeze (copied).
    """

    def __init__(self, statistics: RunningMeanStd):
        super().__init__(shape=statistics.mean.shape)
        self.mean = np.array(statistics.mean, dtype=np.float64, copy=True)
        self.var = np.array(statistics.var, dtype=np.float64, copy=True)
        self.count = float(statistics.count)

    def update_from_moments(self, batch_mean: np.ndarray, batch_var: np.ndarray, batch_count: float) -> None:  # noqa: ARG002
        """Ignored: frozen statistics do not move."""


def freeze_observation_statistics(normalizer: VecNormalize) -> VecNormalize:
    """Freeze a ``VecNormalize``'s observation statistics in place; its reward statistics still learn
    while ``normalizer.training`` is True.

    A fine-tuned policy was trained on inputs normalised by the statistics it comes with; were they to
    go on moving (``VecNormalize`` with ``training=True``), the inputs of even a frozen network would
    change under it.

    :param normalizer: the ``VecNormalize`` (e.g. loaded from a trained model's ``vecnormalize.pkl``).
    :return: the same object.
    """
    if isinstance(normalizer.obs_rms, dict):
        normalizer.obs_rms = {key: FrozenRunningMeanStd(rms) for key, rms in normalizer.obs_rms.items()}
    else:
        normalizer.obs_rms = FrozenRunningMeanStd(normalizer.obs_rms)
    return normalizer


def observation_statistics_frozen(normalizer: VecNormalize) -> bool:
    """Whether every observation statistic of ``normalizer`` is frozen (see :func:`freeze_observation_statistics`)."""
    statistics = normalizer.obs_rms.values() if isinstance(normalizer.obs_rms, dict) else [normalizer.obs_rms]
    return all(isinstance(rms, FrozenRunningMeanStd) for rms in statistics)


def freeze(modules: Iterable[nn.Module]) -> int:
    """``requires_grad = False`` on every parameter of ``modules``; returns how many elements."""
    count = 0
    for module in modules:
        for p in module.parameters():
            p.requires_grad_(False)
            count += p.numel()
    return count


def critic_modules(policy: nn.Module) -> list[nn.Module]:
    """The modules only an actor-critic policy's value depends on (a shared extractor is not one)."""
    modules = [policy.mlp_extractor.value_net, policy.value_net]
    return modules if policy.share_features_extractor else [policy.vf_features_extractor, *modules]


class CriticWarmup(BaseCallback):
    """Train only the critic for the first ``steps`` env steps of a run that starts from a trained actor.

    A fine-tuned actor arrives without a critic for the new task (a distilled student's critic was
    never trained; a teacher's valued another reward), and PPO's first updates then follow the
    advantages of an arbitrary value function, away from what the actor knows. During the warm-up
    the actor's parameters do not require gradients, so they get none and Adam skips them (no
    state is built up that would jolt them when the warm-up ends); the policy loss is computed and
    logged as usual. The updates of the rollouts that end within the first ``steps`` env steps are
    critic-only; a run resumed within the warm-up continues it, one resumed after it trains both.

    :param steps: env steps of critic-only training (0: none).
    """

    def __init__(self, steps: int):
        super().__init__()
        if steps < 0:
            raise ValueError(f"critic warm-up must be >= 0 env steps, got {steps}")
        self.steps = steps
        self._frozen: list[nn.Parameter] = []

    def _on_training_start(self) -> None:
        if self.model.num_timesteps < self.steps:
            policy = self.model.policy
            critic = {id(p) for module in critic_modules(policy) for p in module.parameters()}
            self._frozen = [p for p in policy.parameters() if p.requires_grad and id(p) not in critic]
            for p in self._frozen:
                p.requires_grad_(False)

    def _on_rollout_end(self) -> None:
        # called after collection, before the update: updates on the first ``steps`` env steps are critic-only
        if self._frozen and self.model.num_timesteps > self.steps:
            for p in self._frozen:
                p.requires_grad_(True)
            self._frozen = []

    def _on_step(self) -> bool:
        return True

    @property
    def active(self) -> bool:
        """Whether the actor is frozen now."""
        return bool(self._frozen)


def critic_rate_scales(policy: nn.Module, scale: float) -> dict[nn.Parameter, th.Tensor]:
    """``{parameter: scale}`` for every trainable parameter of the critic (:func:`critic_modules`),
    for :class:`UnitLearningRates`: the critic then learns at ``scale`` times the optimiser's rate."""
    return {p: th.full((), float(scale)) for module in critic_modules(policy) for p in module.parameters() if p.requires_grad}


def rotation_rate_scales(policy: nn.Module, scale: float) -> dict[nn.Parameter, th.Tensor]:
    """``{Cayley generator: scale}`` for every orthogonal factorized layer of a policy, for
    :class:`UnitLearningRates`: its rotations then turn at ``scale`` times the optimiser's rate (0: frozen)."""
    return {
        layer.square_skew: th.full((), float(scale))
        for layer in policy.modules()
        if isinstance(layer, FactorizedLinear) and layer.orthogonal and layer.square_skew.requires_grad
    }


def actor_modules(policy: nn.Module) -> list[nn.Module]:
    """The modules a DivMorph policy's actions depend on (router excluded)."""
    extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
    return [extractor, policy.mlp_extractor.policy_net, policy.action_net]


def unit_groups(layer: FactorizedLinear, unit: th.Tensor) -> dict[str, dict[nn.Parameter, th.Tensor]]:
    """Masks of a layer's learngene and selected-tailor elements (singular values, tall factor),
    for measuring the update ratio actually applied."""
    is_learngene = th.zeros(layer.rank, dtype=th.bool)
    is_learngene[: layer.n_learngenes] = True
    is_selected = ~is_learngene & (unit > 0)
    return {
        name: {layer.singular_values: mask.clone(), layer.tall: mask.expand_as(layer.tall).clone()}
        for name, mask in (("learngene", is_learngene), ("selected_tailor", is_selected))
    }


#: The DivMorph-way transfer recipes (``transfer.recipe``): which parameters train under the fixed gates.
#: ``fixed-gates`` (the paper's): selected tailors 1x, learngenes and the rest of the actor
#: ``learngene_scale``; ``singular-values`` (FINE's rule): only the singular values of the active units
#: (learngenes and selected tailors) at the full rate, every other actor parameter frozen; ``kind``
#: (KIND's rule for a large task shift): as ``fixed-gates``, with the selected task tailors re-initialised
#: first (:func:`reinitialise_task_tailors`: the old task's knowledge dropped, the learngenes kept);
#: ``adapter`` (LoRA's rule): only a zero-initialised low-rank adapter on every factorized actor layer
#: trains, at the full rate, every factor and every other actor parameter frozen (the policy must be
#: built with ``adapter_rank > 0``).
RECIPES = ("fixed-gates", "singular-values", "kind", "adapter")

#: Adam's ``eps`` during transfer: far below a distilled student's smallest useful gradients.
TRANSFER_ADAM_EPS = 1e-10


def _divertible_parts(policy: nn.Module) -> dict[str, list[nn.Module]]:
    """The actor's parts that diversion can factorise, by the config key that diverts them: the
    Transformer encoder, and the decoder (its hidden layers and the action head)."""
    extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
    return {"divert_transformer": [extractor.encoder], "divert_decoder": [policy.mlp_extractor.policy_net, policy.action_net]}


def undiverted_modules(policy: nn.Module) -> list[nn.Module]:
    """The actor parts a DivMorph ablation does not divert: the Transformer encoder with
    ``divert_transformer=False``, the decoder (hidden layers and action head) with
    ``divert_decoder=False``; empty for the full DivMorph."""
    config = getattr(policy, "config", {})
    return [part for key, parts in _divertible_parts(policy).items() if not config.get(key, True) for part in parts]


def diverted_modules(policy: nn.Module) -> list[nn.Module]:
    """The actor parts a DivMorph policy diverts (those with tailors): of the Transformer encoder and
    the decoder, those an ablation does not leave out (:func:`undiverted_modules`)."""
    config = getattr(policy, "config", {})
    return [part for key, parts in _divertible_parts(policy).items() if config.get(key, True) for part in parts]


def set_adam_eps(optimizer: th.optim.Optimizer, eps: float) -> None:
    """Set ``eps`` in every parameter group of an Adam-type optimiser (those without one are left)."""
    for group in optimizer.param_groups:
        if "eps" in group:
            group["eps"] = eps


def prepare_transfer(
    policy: nn.Module,
    selection: UnitSelection,
    learngene_scale: float = 0.1,
    adam_eps: float | None = TRANSFER_ADAM_EPS,
    undiverted_scale: float | None = 1.0,
    critic_scale: float = 1.0,
    rotation_scale: float = 1.0,
    recipe: str = "fixed-gates",
) -> UnitLearningRates:
    """Set a DivMorph policy up for DivMorph transfer, in place.

    * the router (morphology encoder and both gates) is frozen, so the gates stay fixed;
    * every square factor is re-based (its rotation folded into the base, the skew restarted at
      zero), so that unselected tailors stay exactly frozen (see the module docstring);
    * in every factorized actor layer, selected tailors train at the full learning rate, the
      learngenes at ``learngene_scale`` of it, unselected tailors not at all;
    * the actor's other parameters (token embedding, layer norms, biases, exteroception
      encoders), which carry shared knowledge like the learngenes, train at ``learngene_scale``;
    * in an ablation, a part it does not divert (:func:`undiverted_modules`: it has no tailors, so
      every unit of it would count as a learngene) and every parameter outside the parts it diverts
      (embedding, exteroception encoders) train at ``undiverted_scale`` -- by default the full rate,
      as in the dense student, so that the ablation differs from DivMorph in its diversion, not in
      learning rates; inside its diverted part the rule is DivMorph's;
    * the critic (never distilled) trains at ``critic_scale`` times the full rate;
    * the Cayley generators of the square factors train at ``rotation_scale`` times their units'
      rate (:func:`factor_parameter_scales`);
    * the optimiser's ``eps`` is set to ``adam_eps`` so that Adam normalises even the small
      gradients of a distilled student and the configured ratio is the one applied.

    :param policy: a :class:`~sb3_divmorph.policies.DivMorphPolicy` (its optimiser must exist).
    :param selection: the tailors the fixed gates select (:meth:`UnitSelection.from_gates`).
    :param learngene_scale: learning-rate ratio of the shared knowledge to the selected tailors.
    :param adam_eps: ``eps`` for every parameter group of the optimiser; ``None`` keeps it.
    :param undiverted_scale: learning-rate scale of the parts an ablation does not divert;
        ``None``: ``learngene_scale`` (every unit of such a part trained as a learngene).
    :param critic_scale: learning-rate scale of the critic (:func:`critic_rate_scales`).
    :param rotation_scale: learning-rate scale of every Cayley generator relative to its units'.
    :param recipe: one of :data:`RECIPES`; ``singular-values`` then trains, in the actor, only the
        singular values of the units the gates keep active (learngenes and selected tailors) at the
        full rate (the scales above apply to ``fixed-gates``); ``kind`` re-initialises the selected
        task tailors (:func:`reinitialise_task_tailors`), then trains as ``fixed-gates``; ``adapter``
        trains only the layers' adapters (:func:`adapter_scales`).
    :return: the installed :class:`UnitLearningRates` (keep it, or call ``remove``); its
        :meth:`~UnitLearningRates.measured_ratio` is the learngene / selected-tailor update ratio
        (units of undiverted parts are measured apart, as the group ``undiverted``).
    """
    if not hasattr(policy, "router"):
        raise TypeError(f"transfer with fixed gates needs a DivMorphPolicy, got {type(policy).__name__}")
    if not 0 <= learngene_scale <= 1:
        raise ValueError(f"learngene_scale must be in [0, 1], got {learngene_scale}")
    if undiverted_scale is None:
        undiverted_scale = learngene_scale
    if not 0 <= undiverted_scale <= 1:
        raise ValueError(f"undiverted_scale must be in [0, 1] (or None), got {undiverted_scale}")
    if not 0 <= rotation_scale <= 1:
        raise ValueError(f"rotation_scale must be in [0, 1], got {rotation_scale}")
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {list(RECIPES)}, got {recipe!r}")
    freeze([policy.router])
    optimizer = policy.optimizer
    if recipe == "kind":
        reinitialise_task_tailors(policy, selection)
    scales: dict[nn.Parameter, th.Tensor] = {}
    groups: dict[str, dict[nn.Parameter, th.Tensor]] = {"learngene": {}, "selected_tailor": {}, "undiverted": {}}
    undiverted = undiverted_modules(policy)
    for part in undiverted:
        for layer in part.modules():
            if isinstance(layer, FactorizedLinear):
                layer.rebase_square_factor()
                if layer.orthogonal:
                    optimizer.state.pop(layer.square_skew, None)
                unit = th.full((layer.rank,), float(undiverted_scale))
                scales.update(factor_parameter_scales(layer, unit, undiverted_scale, rotation_scale))
                groups["undiverted"].update(unit_groups(layer, unit)["learngene"])
        for p in part.parameters():
            if p.requires_grad and p not in scales:
                scales[p] = th.full((), float(undiverted_scale))
    handled = {id(layer) for part in undiverted for layer in part.modules()}
    # outside the diverted parts: shared knowledge in DivMorph, an ordinary fine-tuned network in an ablation
    inside = {p for part in diverted_modules(policy) for p in part.parameters()}
    outside_scale = undiverted_scale if undiverted else learngene_scale
    for module in actor_modules(policy):
        for layer in module.modules():
            if isinstance(layer, FactorizedLinear) and id(layer) not in handled:
                layer.rebase_square_factor()
                if layer.orthogonal:
                    # Adam's moments of the skew belonged to the old parametrisation
                    optimizer.state.pop(layer.square_skew, None)
                unit = unit_scales(layer, selection, learngene_scale)
                scales.update(factor_parameter_scales(layer, unit, learngene_scale, rotation_scale))
                for name, masks in unit_groups(layer, unit).items():
                    groups[name].update(masks)
        for p in module.parameters():
            if p.requires_grad and p not in scales:
                scales[p] = th.full((), float(learngene_scale if p in inside else outside_scale))
    if isinstance(getattr(policy, "log_std", None), nn.Parameter):
        scales[policy.log_std] = th.full((), float(outside_scale))
    if recipe == "singular-values":
        scales = singular_value_scales(policy, scales)
    elif recipe == "adapter":
        scales = adapter_scales(policy, scales)
        groups["adapter"] = {p: th.ones((), dtype=th.bool) for p in adapter_parameters(policy)}
    scales.update(critic_rate_scales(policy, critic_scale))
    if adam_eps is not None:
        set_adam_eps(optimizer, adam_eps)
    return UnitLearningRates(optimizer, scales, groups)


@th.no_grad()
def reinitialise_task_tailors(policy: nn.Module, selection: UnitSelection) -> int:
    """KIND's start for a large task shift: in every factorised actor layer, each task tailor the
    fixed gates select gets a fresh random direction in its tall factor and a zero singular value.

    The old task's tailors leave the function (what the student knew of the training task whose gates
    it was given), the learngenes and morphology tailors stay; with a zero singular value the new
    unit adds nothing until training grows it, and its direction learns once it does (as a
    zero-initialised adapter). Square factors, being orthogonal, are left as they are.

    :return: the number of units re-initialised.
    """
    count = 0
    for module in actor_modules(policy):
        for layer in module.modules():
            if not isinstance(layer, FactorizedLinear) or layer.n_task_tailors == 0:
                continue
            task = layer.unit_slices["task"]
            if len(selection.task) != layer.n_task_tailors:
                raise ValueError(f"a selection of {len(selection.task)} task tailors for a layer with {layer.n_task_tailors}")
            chosen = th.as_tensor(selection.task, dtype=th.bool)
            units = th.arange(task.start, task.stop)[chosen]
            if len(units) == 0:
                continue
            fresh = th.randn(layer.tall.shape[0], len(units), dtype=layer.tall.dtype, device=layer.tall.device)
            layer.tall[:, units] = fresh / fresh.norm(dim=0, keepdim=True)  # unit columns, as the SVD's
            layer.singular_values[units] = 0.0
            layer._cache = None
            count += len(units)
    return count


def adapter_parameters(policy: nn.Module) -> list[nn.Parameter]:
    """The adapters' parameters of every factorized actor layer (empty without ``adapter_rank``)."""
    layers = [layer for module in actor_modules(policy) for layer in module.modules() if isinstance(layer, FactorizedLinear)]
    return [p for layer in layers if layer.adapter_rank for p in (layer.adapter_down, layer.adapter_up)]


def adapter_scales(policy: nn.Module, scales: Mapping[nn.Parameter, th.Tensor]) -> dict[nn.Parameter, th.Tensor]:
    """LoRA's rule on top of :func:`prepare_transfer`'s scales: in the actor, the adapters train at the
    full rate and every other parameter (factors, biases, embeddings, encoders, std) is frozen.

    :raises ValueError: the policy has no adapters (build it with ``adapter_rank > 0``).
    """
    adapters = adapter_parameters(policy)
    if not adapters:
        raise ValueError(
            "recipe 'adapter' trains the low-rank adapters of the factorized layers, but this policy has none: "
            "build it with DivMorphPolicy(adapter_rank=...) (the pipeline's transfer.adapter_rank)"
        )
    return _actor_trains_only(policy, scales, {p: th.ones(()) for p in adapters})


def singular_value_scales(policy: nn.Module, scales: Mapping[nn.Parameter, th.Tensor]) -> dict[nn.Parameter, th.Tensor]:
    """FINE's rule on top of :func:`prepare_transfer`'s scales: in the actor, the singular values of
    every active unit (a non-zero scale) train at the full rate and every other parameter is frozen."""
    singular = [
        layer.singular_values for module in actor_modules(policy) for layer in module.modules() if isinstance(layer, FactorizedLinear)
    ]
    return _actor_trains_only(policy, scales, {p: (scales[p] > 0).float() if p in scales else th.ones(()) for p in singular})


def _actor_trains_only(
    policy: nn.Module, scales: Mapping[nn.Parameter, th.Tensor], trained: Mapping[nn.Parameter, th.Tensor]
) -> dict[nn.Parameter, th.Tensor]:
    """``scales`` with every actor parameter (and a learned std) frozen except ``trained``, at its own scale."""
    frozen = {p: th.zeros(()) for p in scales if p not in trained}
    frozen.update(
        {p: th.zeros(()) for module in actor_modules(policy) for p in module.parameters() if p.requires_grad and p not in trained}
    )
    if isinstance(getattr(policy, "log_std", None), nn.Parameter):
        frozen[policy.log_std] = th.zeros(())
    return {**frozen, **trained}
