"""MetaMorph's training recipe for Stable-Baselines3: the cosine learning-rate schedule with warm-up
and the balanced robot sampler.

MetaMorph (and ModuMorph / HyperDistill, which train their teachers the same way) differs from a
plain SB3 PPO setup in a few places (spec §6.1). What it takes to run that setup with SB3:

==============================  ===========================================================
MetaMorph                       here
==============================  ===========================================================
lr 3e-4, cosine decay to 0,     ``learning_rate: cosine_3e-4`` in a zoo entry (warm-up over
linear warm-up over the first   the first ``5/1220`` of training, from 0.1x) or
5 of 1220 iterations from 0.1x  :class:`CosineWarmupSchedule` directly
Adam eps 1e-5                   ``policy_kwargs: dict(optimizer_kwargs=dict(eps=1e-5))``
stop the epoch loop at approx   ``target_kl: 0.1333`` (SB3 stops at ``1.5 x target_kl``, so
KL > 20 x 0.01                  0.2; ModuMorph's coefficient 5: ``0.0333``)
observation (proprioception)    ``normalize: dict(norm_obs=True, norm_reward=True,
and return normalisation,       norm_obs_keys=['proprioceptive'], clip_obs=10.0,
clip 10                         clip_reward=10.0)``
balanced robot sampling         :class:`BalancedRobotSampler` (profile / zoo entry
                                ``sampler: balanced``)
==============================  ===========================================================

The zoo entries ``Unimal-<task>-v0-metamorph`` (``zoo_configs/ppo.yml``) combine all of them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback


class CosineWarmupSchedule:
    """SB3 learning-rate schedule: linear warm-up from ``warmup_start x initial``, then cosine decay to 0.

    SB3 calls a schedule with ``progress_remaining`` going from 1 (start) to 0 (end), so the schedule
    is defined over the fraction of training done, ``f = 1 - progress_remaining``:
    ``lr(f) = initial x (warmup_start + (1 - warmup_start) f / w)`` for ``f < w``, then
    ``initial x 0.5 (1 + cos(pi (f - w) / (1 - w)))``. MetaMorph warms up over its first 5 of 1220
    iterations (``w = 5/1220``) and decays over all of them; its decay starts at iteration 0, which
    differs from starting after the warm-up by less than 1e-4 of the rate.

    :param initial: the peak learning rate (MetaMorph 3e-4).
    :param warmup_fraction: fraction of training spent warming up (MetaMorph 5/1220).
    :param warmup_start: the warm-up starts at this fraction of ``initial`` (MetaMorph 0.1).
    """

    def __init__(self, initial: float, warmup_fraction: float = 5 / 1220, warmup_start: float = 0.1):
        if initial <= 0 or not 0 <= warmup_fraction < 1 or not 0 <= warmup_start <= 1:
            raise ValueError(
                f"cosine schedule needs initial > 0, 0 <= warmup_fraction < 1, 0 <= warmup_start <= 1; "
                f"got {initial}, {warmup_fraction}, {warmup_start}"
            )
        self.initial, self.warmup_fraction, self.warmup_start = float(initial), float(warmup_fraction), float(warmup_start)

    def __call__(self, progress_remaining: float) -> float:
        done = min(max(1.0 - progress_remaining, 0.0), 1.0)
        w = self.warmup_fraction
        if done < w:
            return self.initial * (self.warmup_start + (1.0 - self.warmup_start) * done / w)
        return self.initial * 0.5 * (1.0 + math.cos(math.pi * (done - w) / (1.0 - w)))

    def __repr__(self) -> str:
        return f"CosineWarmupSchedule({self.initial}, warmup_fraction={self.warmup_fraction}, warmup_start={self.warmup_start})"


def balanced_probabilities(mean_lengths: Sequence[float | None], scale: float = 1000.0, power: float = 1.0) -> np.ndarray:
    """MetaMorph's robot probabilities: ``p_i ∝ (scale / EMA of robot i's episode length) ** power``.

    Robots with short episodes (they fall early, i.e. are hard) are drawn more often. A robot with no
    finished episode yet gets the mean of the others' lengths (uniform when none has any).

    :param mean_lengths: per robot, the EMA of its episode lengths (``None`` = not seen yet).
    :param scale: MetaMorph's 1000 (cancels out after normalisation; kept for readability).
    :param power: MetaMorph's 1.
    """
    known = [x for x in mean_lengths if x is not None]
    if not known:
        return np.full(len(mean_lengths), 1.0 / len(mean_lengths))
    fill = float(np.mean(known))
    lengths = np.array([fill if x is None else x for x in mean_lengths], dtype=np.float64)
    weights = (scale / np.maximum(lengths, 1.0)) ** power
    return weights / weights.sum()


class BalancedRobotSampler(BaseCallback):
    """MetaMorph's "balanced" robot sampling for multi-robot PPO.

    Keeps an exponential moving average (``alpha`` 0.1) of each robot's episode length from the
    training episodes (``info["episode"]["l"]`` of ``Monitor``/``VecMonitor`` and
    ``info["morphology"]``). For the first ``warmup_iterations`` rollouts robots are drawn
    uniformly; after every later rollout the probabilities :func:`balanced_probabilities` are sent
    to every env worker (``VecEnv.env_method("set_morphology_probabilities", p)``), which draws the
    robot of each new episode with them. MetaMorph re-draws a per-iteration list of robots; drawing
    each episode's robot with the same probabilities has the same distribution.

    :param warmup_iterations: rollouts before sampling becomes balanced (MetaMorph 30).
    :param alpha: EMA weight of a new episode length (MetaMorph 0.1).
    :param power: exponent on ``1000 / EMA`` (MetaMorph 1).
    :param verbose: SB3 verbosity.
    """

    def __init__(self, warmup_iterations: int = 30, alpha: float = 0.1, power: float = 1.0, verbose: int = 0):
        super().__init__(verbose)
        if warmup_iterations < 0 or not 0 < alpha <= 1:
            raise ValueError(f"need warmup_iterations >= 0 and 0 < alpha <= 1, got {warmup_iterations}, {alpha}")
        self.warmup_iterations, self.alpha, self.power = int(warmup_iterations), float(alpha), float(power)
        self.ema: dict[str, float] = {}
        self.iterations = 0
        self.probabilities: np.ndarray | None = None
        self._names: list[str] | None = None

    def record(self, morphology: str, length: float) -> None:
        """Fold one finished episode of ``morphology`` into its EMA."""
        old = self.ema.get(morphology)
        self.ema[morphology] = float(length) if old is None else (1.0 - self.alpha) * old + self.alpha * float(length)

    def record_infos(self, infos: Iterable[dict[str, Any]]) -> None:
        """Fold the finished episodes found in a step's ``infos``."""
        for info in infos:
            episode = info.get("episode")
            if episode is not None and "morphology" in info:
                self.record(info["morphology"], episode["l"])

    def probabilities_for(self, names: Sequence[str]) -> np.ndarray:
        """Current balanced probabilities over ``names``."""
        return balanced_probabilities([self.ema.get(n) for n in names], power=self.power)

    def _on_training_start(self) -> None:
        self._names = list(self.training_env.get_attr("morphology_names", indices=[0])[0])

    def _on_step(self) -> bool:
        self.record_infos(self.locals.get("infos", ()))
        return True

    def _on_rollout_end(self) -> None:
        self.iterations += 1
        if self.iterations < self.warmup_iterations or not self.ema:
            return
        assert self._names is not None  # read at the training start
        self.probabilities = self.probabilities_for(self._names)
        self.training_env.env_method("set_morphology_probabilities", self.probabilities)
        p = self.probabilities
        self.logger.record("sampler/max_over_min_probability", float(p.max() / max(p.min(), 1e-12)))
        self.logger.record("sampler/robots_seen", len(self.ema))
