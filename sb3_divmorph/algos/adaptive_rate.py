"""A learning rate that targets a KL per PPO update, whatever the policy's parameterisation.

Two policies fine-tuned at one nominal rate can move very differently: a step of Adam on a Cayley
generator or a tall factor changes a DivMorph student's function several times more than the same
step on a dense weight, because it turns or stretches whole singular directions. Comparing transfer
recipes at equal *effect* means giving each the step size that moves its policy by a set amount.

:class:`AdaptiveLearningRate` does what rsl_rl's ``desired_kl`` does, once per update instead of once
per minibatch: after every PPO update it reads the update's approximate KL (SB3's
``train/approx_kl``) and multiplies the learning rate by ``1 / factor`` when the KL was above
``2 x desired_kl`` and by ``factor`` when it was below ``desired_kl / 2``. The multiplier applies on
top of the run's schedule (``lin_1e-4`` keeps decaying) and to every per-unit rate derived from it
(:class:`~sb3_divmorph.algos.finetune.UnitLearningRates` scales updates, not rates). It lives in the
model (``model.learning_rate_multiplier``, saved with it), so a resumed run goes on from it.
"""

from __future__ import annotations

from collections.abc import Callable

from stable_baselines3.common.callbacks import BaseCallback


class ScaledSchedule:
    """A learning-rate schedule times an adjustable ``scale``.

    :param base: the schedule (``progress_remaining -> rate``).
    :param scale: the multiplier.
    """

    def __init__(self, base: Callable[[float], float], scale: float = 1.0):
        self.base = base
        self.scale = float(scale)

    def __call__(self, progress_remaining: float) -> float:
        return float(self.base(progress_remaining)) * self.scale


class AdaptiveLearningRate(BaseCallback):
    """Adapt the learning rate after every PPO update so that its approximate KL stays near ``desired_kl``.

    :param desired_kl: the KL an update should have (rsl_rl's default 0.01).
    :param factor: the multiplier of one adaptation (rsl_rl: 1.5).
    :param bounds: the smallest and largest multiplier of the schedule's rate.
    """

    def __init__(self, desired_kl: float, factor: float = 1.5, bounds: tuple[float, float] = (1e-3, 1e3)):
        super().__init__()
        if not desired_kl > 0:
            raise ValueError(f"desired_kl must be > 0, got {desired_kl}")
        if not factor > 1:
            raise ValueError(f"factor must be > 1, got {factor}")
        self.desired_kl, self.factor, self.bounds = float(desired_kl), float(factor), bounds
        self._seen_updates = -1
        #: ``(update count, approximate KL, multiplier after the adaptation)`` of every adaptation
        self.history: list[tuple[int, float, float]] = []

    @property
    def schedule(self) -> ScaledSchedule:
        return self.model.lr_schedule  # type: ignore[return-value]

    def _on_training_start(self) -> None:
        # SB3 rebuilds the schedule from ``learning_rate`` when it loads a model: the multiplier is kept
        # as an attribute of the model (saved with it), and the schedule wrapped again around it
        if not isinstance(self.model.lr_schedule, ScaledSchedule):
            self.model.lr_schedule = ScaledSchedule(self.model.lr_schedule, getattr(self.model, "learning_rate_multiplier", 1.0))
        self._seen_updates = self.model._n_updates

    def _on_rollout_start(self) -> None:
        # the previous update's KL, recorded by PPO.train and not yet dumped (dumps happen after collection)
        kl = self.model.logger.name_to_value.get("train/approx_kl")
        if kl is None or self.model._n_updates == self._seen_updates:
            return
        self._seen_updates = self.model._n_updates
        low, high = self.bounds
        if kl > 2 * self.desired_kl:
            self.schedule.scale = max(low, self.schedule.scale / self.factor)
        elif kl < self.desired_kl / 2:
            self.schedule.scale = min(high, self.schedule.scale * self.factor)
        self.model.learning_rate_multiplier = self.schedule.scale  # type: ignore[attr-defined]
        self.history.append((self.model._n_updates, float(kl), self.schedule.scale))
        self.logger.record("train/learning_rate_multiplier", self.schedule.scale)

    def _on_step(self) -> bool:
        return True
