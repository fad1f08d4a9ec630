"""Transfer metrics per task, arm and robot split, from the runs' evaluation curves, with confidence intervals.

Every transfer run evaluates its policy deterministically on each robot of a split, ``eval_episodes``
episodes per robot, at step 0 and every ``eval_every`` env steps (:mod:`divmorph.pipeline.curves`).
For each arm this gives a return per seed, robot and evaluation step (the mean over the robot's
episodes); every metric is the mean over seeds and robots of a per-(seed, robot) value:

* **zero-shot return**: the evaluation at step 0, before any training on the task;
* **final return**: the last evaluation;
* **AUC**: the area under the evaluation curve (trapezoids over env steps) divided by the steps it
  spans, i.e. the mean return over training, in return units;
* **steps to the level** (the sample-efficiency figure): the env step from which the arm's mean
  curve reaches the task's *level* and stays at or above it until the end of its budget (linear
  between evaluations), ``None`` ("not held") when its last evaluation is below it. The level is
  :data:`EFFICIENCY_FRACTION` of the way from ``scratch``'s zero-shot return (the untrained start)
  to the best arm's final return on that task and split (the best final return when there is no
  ``scratch``: the lowest zero-shot return): fixed before any run was looked at, the same for
  every arm, and reached only by an arm that ends near the best arm's final return -- an arm that
  starts high and falls is not credited with a speed-up it did not show;
* **speed-up vs scratch**: scratch's steps to the level / the arm's, only when both hold it; a
  lower bound (``>=``, stated) when the arm holds it and scratch never does; "from the start" when
  the arm holds it from step 0 (the one case whose ratio is infinite, stated as such).

Uncertainty: ``*_sd`` is the sd over seeds of the per-seed means (as before); ``*_lo`` / ``*_hi``
are a 95% bootstrap percentile interval over robots *and* seeds: each of :data:`BOOTSTRAP` draws
resamples the seeds with replacement and, independently, the robots with replacement, and computes
the metric on the resampled mean curve. With one seed the interval covers robot-to-robot variation
only. The interval of the steps to the level may end in ``inf`` (some draws never hold it);
``held`` is the fraction of draws that hold it.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Fraction of the budget whose evaluations define a curve's final level (:func:`final_level`).
FINAL_FRACTION = 0.1
#: The level of the sample-efficiency figure: this fraction of the way from scratch's zero-shot
#: return to the best arm's final return (fixed a priori, see the module docstring).
EFFICIENCY_FRACTION = 0.8
#: Bootstrap draws of the confidence intervals.
BOOTSTRAP = 2000
#: Coverage of the confidence intervals.
CONFIDENCE = 0.95
#: The arm whose zero-shot return anchors the level and against which speed-ups are given.
REFERENCE_ARM = "scratch"


def final_level(steps: np.ndarray, returns: np.ndarray, fraction: float = FINAL_FRACTION) -> float:
    """Mean return of the evaluations in the last ``fraction`` of the steps (at least the last one)."""
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if not len(steps):
        raise ValueError("an empty curve has no final return")
    start, end = steps.min(), steps.max()
    tail = steps >= end - fraction * (end - start)
    return float(returns[tail].mean())


def steps_to_hold(steps: np.ndarray, returns: np.ndarray, level: float) -> float | None:
    """The env step from which the curve is at or above ``level`` until its end (linear between
    evaluations); the first step when it never drops below; ``None`` when its last value is below.

    :param steps: (T,) increasing evaluation steps.
    :param returns: (T,) the curve.
    :param level: the return to reach and hold.
    """
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if not len(steps) or returns[-1] < level:
        return None
    below = np.flatnonzero(returns < level)
    if not len(below):
        return float(steps[0])
    i = int(below[-1])
    x0, x1, y0, y1 = steps[i], steps[i + 1], returns[i], returns[i + 1]
    return float(x0 + (level - y0) / (y1 - y0) * (x1 - x0))


def area_under_curve(steps: np.ndarray, returns: np.ndarray) -> float:
    """Trapezoid area divided by the steps spanned: the mean return over training."""
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if len(steps) < 2 or steps[-1] == steps[0]:
        return float(returns.mean())
    return float(np.trapezoid(returns, steps) / (steps[-1] - steps[0]))


def _areas(steps: np.ndarray, curves: np.ndarray) -> np.ndarray:
    """:func:`area_under_curve` of each row of ``curves`` (..., T)."""
    if len(steps) < 2 or steps[-1] == steps[0]:
        return curves.mean(-1)
    return np.trapezoid(curves, steps, axis=-1) / (steps[-1] - steps[0])


def mean_curve(curves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(steps, mean, sd)`` over seeds, on :func:`common_grid` (each seed linear between its evaluations)."""
    grid = common_grid([np.asarray(s, float) for s, _ in curves]) if curves else np.array([])
    if not len(grid):
        return np.array([]), np.array([]), np.array([])
    values = np.array([on_grid(np.asarray(s, float), np.asarray(r, float), grid) for s, r in curves])
    return grid, values.mean(0), values.std(0)


def common_grid(steps: list[np.ndarray]) -> np.ndarray:
    """The steps at which seeds' curves are compared: every seed's evaluation steps (their union) within
    the span all of them cover; empty when they cover no common span.

    Seeds need not evaluate at the same steps: a run resumed from a checkpoint evaluates there and
    every ``eval_every`` steps from it, so resumed seeds' steps drift apart (the exact steps they share
    can be step 0 alone).
    """
    if not steps or any(not len(s) for s in steps):
        return np.array([])
    start, end = max(s.min() for s in steps), min(s.max() for s in steps)
    grid = np.unique(np.concatenate(steps))
    return grid[(grid >= start) & (grid <= end)]


def on_grid(steps: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``values`` (..., T) at ``steps`` read at ``grid`` (linear between evaluations, as the metrics assume)."""
    flat = values.reshape(-1, len(steps))
    return np.array([np.interp(grid, steps, row) for row in flat]).reshape(*values.shape[:-1], len(grid))


@dataclass
class RobotCurves:
    """One run's evaluations on one split: the mean return over episodes per robot and step.

    :param steps: (T,) evaluation steps.
    :param robots: the R robots' names.
    :param values: (R, T) returns.
    """

    steps: np.ndarray
    robots: list[str]
    values: np.ndarray

    @classmethod
    def from_rows(cls, rows: Iterable[Mapping[str, Any]], split: str) -> RobotCurves:
        """From ``eval.csv`` rows (``timesteps, split, robot, episode, return``); a step at which some
        robot has no evaluation (a run killed mid-evaluation) is left out."""
        by_key: dict[tuple[str, int], list[float]] = defaultdict(list)
        for row in rows:
            if row["split"] == split:
                by_key[(str(row["robot"]), int(row["timesteps"]))].append(float(row["return"]))
        robots = sorted({robot for robot, _ in by_key})
        steps = sorted({step for _, step in by_key if all((robot, step) in by_key for robot in robots)})
        values = np.array([[np.mean(by_key[(robot, step)]) for step in steps] for robot in robots]).reshape(len(robots), len(steps))
        return cls(np.array(steps, float), robots, values)

    def mean(self) -> tuple[np.ndarray, np.ndarray]:
        """``(steps, mean over robots)``."""
        return self.steps, self.values.mean(0)


def stack_seeds(runs: list[RobotCurves]) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, values (S, R, T))`` on :func:`common_grid` and the robots every seed has.

    :raises ValueError: the seeds' evaluations cover no common span or share no robot.
    """
    grid = common_grid([r.steps for r in runs])
    robots = sorted(set.intersection(*(set(r.robots) for r in runs)))
    if not len(grid) or not robots:
        raise ValueError("the seeds' evaluations cover no common span of steps or share no robot")
    values = np.stack([on_grid(r.steps, r.values[[r.robots.index(x) for x in robots]], grid) for r in runs])
    return grid, values


def _counts(rng: np.random.Generator, n: int, draws: int) -> np.ndarray:
    """(draws, n) how many times each of ``n`` units is drawn in each bootstrap draw (with replacement)."""
    return rng.multinomial(n, np.full(n, 1 / n), size=draws).astype(float)


def bootstrap_curves(values: np.ndarray, draws: int = BOOTSTRAP, seed: int = 0) -> np.ndarray:
    """(draws, T) mean curves of ``values`` (S, R, T) with seeds and robots resampled independently,
    each with replacement (a fixed generator: the same intervals on every call)."""
    n_seeds, n_robots, _ = values.shape
    rng = np.random.default_rng(seed)
    seed_counts = _counts(rng, n_seeds, draws)
    robot_counts = _counts(rng, n_robots, draws)
    return np.einsum("bs,br,srt->bt", seed_counts, robot_counts, values) / (n_seeds * n_robots)


def interval(samples: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Nearest-rank percentile interval (works with ``inf`` samples)."""
    ordered = np.sort(np.asarray(samples, float))
    tail = (1 - confidence) / 2
    lo = ordered[int(math.floor(tail * (len(ordered) - 1)))]
    hi = ordered[int(math.ceil((1 - tail) * (len(ordered) - 1)))]
    return float(lo), float(hi)


#: Student's t 97.5% quantiles by degrees of freedom (scipy is not a dependency)
_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571}


def seed_interval(values: np.ndarray) -> tuple[float, float]:
    """95% t interval of the mean of a value per seed (2 to 6 seeds; ``nan`` for fewer than two)."""
    values = np.asarray(values, float)
    if len(values) < 2:
        return np.nan, np.nan
    half = _T975[len(values) - 1] * values.std(ddof=1) / np.sqrt(len(values))
    return values.mean() - half, values.mean() + half


def robot_interval(values: np.ndarray) -> tuple[float, float]:
    """95% bootstrap interval of the mean of per-robot values (robots resampled with replacement)."""
    return interval(bootstrap_curves(np.asarray(values, float)[None, :, None])[:, 0])


def _runs_by_robots(values: np.ndarray) -> np.ndarray:
    """``values`` as a complete (seeds, robots) float array (a row per training run, a column per robot)."""
    values = np.asarray(values, float)
    if values.ndim != 2 or not values.size:
        raise ValueError(f"expected a non-empty (seeds, robots) array, got shape {values.shape}")
    if np.isnan(values).any():
        # a missing (seed, robot) cell would change the number of robots a draw averages per seed
        raise ValueError("a (seeds, robots) array with missing values: keep the robots every seed has")
    return values


def run_interval(values: np.ndarray, draws: int = BOOTSTRAP, seed: int = 0) -> tuple[float, float]:
    """95% interval of the mean of ``values`` (S training runs, R robots): a two-way bootstrap resampling
    runs and, independently, robots (:func:`bootstrap_curves`). The training run is the unit that varies:
    a run's robots share its policy, so they are not S x R independent draws. One run: robots only."""
    values = _runs_by_robots(values)
    return interval(bootstrap_curves(values[:, :, None], draws, seed)[:, 0])


def paired_run_interval(values: np.ndarray, comparator: np.ndarray, draws: int = BOOTSTRAP, seed: int = 0) -> tuple[float, float]:
    """95% interval of ``mean(values) - mean(comparator)``, each (its own runs, the same R robots in the same
    order): each draw resamples the runs of each side independently (different training runs) and the robots
    once for both (the difference is paired by robot). A fixed comparator (e.g. a start) is a single row."""
    values, comparator = _runs_by_robots(values), _runs_by_robots(comparator)
    if values.shape[1] != comparator.shape[1]:
        raise ValueError(f"the two sides have {values.shape[1]} and {comparator.shape[1]} robots: pair them by robot first")
    rng = np.random.default_rng(seed)
    # the draws of ``values`` are :func:`run_interval`'s own (the same generator order), the comparator's runs come last
    mine, robots, theirs = _counts(rng, len(values), draws), _counts(rng, values.shape[1], draws), _counts(rng, len(comparator), draws)
    n_robots = values.shape[1]
    means = np.einsum("bs,br,sr->b", mine, robots, values) / (len(values) * n_robots)
    means -= np.einsum("bs,br,sr->b", theirs, robots, comparator) / (len(comparator) * n_robots)
    return interval(means)


def level_for(zero_shots: Mapping[str, float], finals: Mapping[str, float], fraction: float = EFFICIENCY_FRACTION) -> float | None:
    """The sample-efficiency level of a task and split (see the module docstring); ``None`` when no
    arm ends above the start (nothing was learnt that steps could be counted to).

    :param zero_shots: ``{arm: zero-shot return}``.
    :param finals: ``{arm: final return}``.
    """
    if not finals:
        return None
    start = zero_shots[REFERENCE_ARM] if REFERENCE_ARM in zero_shots else min(zero_shots.values())
    best = max(finals.values())
    if not best > start:
        return None
    return float(start + fraction * (best - start))


@dataclass
class ArmMetrics:
    """Metrics of one arm on one task and robot split (see the module docstring)."""

    task: str
    arm: str
    split: str
    seeds: int
    robots: int
    zero_shot: float
    zero_shot_sd: float
    zero_shot_lo: float
    zero_shot_hi: float
    final: float
    final_sd: float
    final_lo: float
    final_hi: float
    auc: float
    auc_sd: float
    auc_lo: float
    auc_hi: float
    #: the task's level (``None``: no arm ends above the start)
    level: float | None
    #: env steps from which the arm holds the level (``None``: it does not by its end)
    steps_to_level: float | None
    steps_lo: float
    steps_hi: float
    #: fraction of bootstrap draws that hold the level
    held: float
    #: scratch's steps to the level / the arm's (``inf``: held from the start; ``None``: not both held)
    efficiency: float | None
    #: ``efficiency`` is a lower bound: the arm holds the level, scratch never does within its budget
    efficiency_bound: bool
    budget: int

    def steps_text(self) -> str:
        """Steps to the level with its interval, e.g. ``12.3k [8.1k, >budget]``."""
        if self.level is None:
            return "no gain over the start"

        def fmt(x: float | None) -> str:
            return ">budget" if x is None or math.isinf(x) else "0" if x == 0 else f"{x / 1000:.1f}k"

        held = "not held" if self.steps_to_level is None else fmt(self.steps_to_level)
        return f"{held} [{fmt(self.steps_lo)}, {fmt(self.steps_hi)}]"

    def efficiency_text(self) -> str:
        """The speed-up vs scratch in words: ``2.10x``, ``>= 3.00x (scratch never held it)``,
        ``from the start (zero-shot)``, or ``-`` when it is not defined."""
        if self.efficiency is None:
            return "-"
        if math.isinf(self.efficiency):
            return "from the start (zero-shot)"
        if self.efficiency_bound:
            return f">= {self.efficiency:.2f}x (scratch never held it)"
        return f"{self.efficiency:.2f}x"


def task_metrics_from_curves(
    task: str, split: str, runs: Mapping[str, list[RobotCurves]], fraction: float = EFFICIENCY_FRACTION, draws: int = BOOTSTRAP
) -> list[ArmMetrics]:
    """Metrics of every arm on one task and split.

    :param runs: ``{arm: [one RobotCurves per seed]}`` (arms without runs are left out).
    :param fraction: see :data:`EFFICIENCY_FRACTION`.
    :param draws: bootstrap draws.
    """
    stacked = {arm: stack_seeds(curves) for arm, curves in runs.items() if curves}
    zero = {arm: float(v[:, :, 0].mean()) for arm, (_, v) in stacked.items()}
    final = {arm: float(v[:, :, -1].mean()) for arm, (_, v) in stacked.items()}
    level = level_for(zero, final, fraction)
    held_steps: dict[str, float | None] = {}
    results: dict[str, dict[str, Any]] = {}
    for arm, (steps, values) in stacked.items():
        per_seed = values.mean(1)  # (S, T)
        boot = bootstrap_curves(values, draws)
        point = values.mean((0, 1))
        held_steps[arm] = None if level is None else steps_to_hold(steps, point, level)
        if level is None:
            boot_steps = np.full(draws, np.inf)
        else:
            boot_steps = np.array([np.inf if (x := steps_to_hold(steps, curve, level)) is None else x for curve in boot])
        z_lo, z_hi = interval(boot[:, 0])
        f_lo, f_hi = interval(boot[:, -1])
        a_lo, a_hi = interval(_areas(steps, boot))
        s_lo, s_hi = interval(boot_steps)
        results[arm] = dict(
            task=task,
            arm=arm,
            split=split,
            seeds=values.shape[0],
            robots=values.shape[1],
            zero_shot=zero[arm],
            zero_shot_sd=float(per_seed[:, 0].std()),
            zero_shot_lo=z_lo,
            zero_shot_hi=z_hi,
            final=final[arm],
            final_sd=float(per_seed[:, -1].std()),
            final_lo=f_lo,
            final_hi=f_hi,
            auc=float(_areas(steps, per_seed).mean()),
            auc_sd=float(_areas(steps, per_seed).std()),
            auc_lo=a_lo,
            auc_hi=a_hi,
            level=level,
            steps_to_level=held_steps[arm],
            steps_lo=s_lo,
            steps_hi=s_hi,
            held=float(np.isfinite(boot_steps).mean()),
            budget=int(steps[-1]),
        )
    reference = held_steps.get(REFERENCE_ARM)
    metrics = []
    for arm, fields in results.items():
        efficiency, bound = speedup(reference, held_steps[arm], results[REFERENCE_ARM]["budget"] if REFERENCE_ARM in results else None)
        metrics.append(ArmMetrics(**fields, efficiency=efficiency, efficiency_bound=bound))
    return metrics


def speedup(reference: float | None, arm: float | None, reference_budget: int | None) -> tuple[float | None, bool]:
    """``(scratch's steps / the arm's, is a lower bound)`` (see the module docstring).

    :param reference: scratch's steps to the level (``None``: never held).
    :param arm: the arm's (``None``: never held).
    :param reference_budget: scratch's budget (``None``: no scratch run).
    """
    if arm is None or reference_budget is None:
        return None, False
    if reference is None:  # scratch never held it within its budget: the arm is at least budget / steps faster
        return (math.inf, False) if arm == 0 else (reference_budget / arm, True)
    if arm == 0:
        return (1.0, False) if reference == 0 else (math.inf, False)
    return reference / arm, False
