"""Transfer metrics per task, arm and robot split, from the runs' evaluation curves.

For each arm (seeds pooled as mean ± sd over seeds, each seed's value being the mean over robots
and episodes of its deterministic evaluations, :mod:`sb3_divmorph.pipeline.curves`):

* **zero-shot return**: the evaluation at step 0, before any training on the task;
* **final return**: the last evaluation;
* **AUC**: the area under the evaluation curve (trapezoids over env steps) divided by the steps it
  spans, i.e. the mean return over training, in return units;
* **sample-efficiency ratio** (the paper's "x times fewer samples"): on the seed-mean curves, the
  env steps ``scratch`` needs to reach its own final return (the mean of its evaluations in the last
  10% of training) divided by the steps the arm needs to reach that same return; crossings are
  linearly interpolated between evaluations. ``None`` (shown ">budget") when the arm never reaches it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Fraction of the budget whose evaluations define scratch's final return.
FINAL_FRACTION = 0.1


def final_level(steps: np.ndarray, returns: np.ndarray, fraction: float = FINAL_FRACTION) -> float:
    """Mean return of the evaluations in the last ``fraction`` of the steps (at least the last one)."""
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if not len(steps):
        raise ValueError("an empty curve has no final return")
    start, end = steps.min(), steps.max()
    tail = steps >= end - fraction * (end - start)
    return float(returns[tail].mean())


def steps_to_reach(steps: np.ndarray, returns: np.ndarray, level: float) -> float | None:
    """First env step at which the curve reaches ``level`` (linear between evaluations); ``None`` if never."""
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    for i, value in enumerate(returns):
        if value >= level:
            if i == 0:
                return float(steps[0])
            x0, x1, y0, y1 = steps[i - 1], steps[i], returns[i - 1], returns[i]
            return float(x0 + (level - y0) / (y1 - y0) * (x1 - x0))
    return None


def sample_efficiency(scratch: tuple[np.ndarray, np.ndarray], arm: tuple[np.ndarray, np.ndarray]) -> float | None:
    """Steps scratch needs to reach its own final return / steps ``arm`` needs to reach it.

    :param scratch: ``(steps, returns)`` of MetaMorph from scratch.
    :param arm: ``(steps, returns)`` of the arm.
    :return: the ratio; ``math.inf`` when the arm starts at that return (step 0) and scratch does
        not; ``None`` when the arm never reaches it within its budget.
    """
    level = final_level(*scratch)
    needed_scratch = steps_to_reach(*scratch, level)
    needed_arm = steps_to_reach(*arm, level)
    if needed_arm is None:
        return None
    assert needed_scratch is not None  # scratch reaches the mean of its own last evaluations
    if needed_arm == 0:
        return math.inf if needed_scratch > 0 else 1.0
    return needed_scratch / needed_arm


def area_under_curve(steps: np.ndarray, returns: np.ndarray) -> float:
    """Trapezoid area divided by the steps spanned: the mean return over training."""
    steps, returns = np.asarray(steps, float), np.asarray(returns, float)
    if len(steps) < 2 or steps[-1] == steps[0]:
        return float(returns.mean())
    return float(np.trapezoid(returns, steps) / (steps[-1] - steps[0]))


def mean_curve(curves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(steps, mean, sd)`` over seeds, on the evaluation steps every seed has."""
    common = sorted(set.intersection(*(set(s.tolist()) for s, _ in curves))) if curves else []
    values = np.array([[r[list(s).index(x)] for x in common] for s, r in curves]) if common else np.zeros((0, 0))
    if not common:
        return np.array([]), np.array([]), np.array([])
    return np.array(common, float), values.mean(0), values.std(0)


@dataclass
class ArmMetrics:
    """Metrics of one arm on one task and robot split (mean and sd over seeds)."""

    task: str
    arm: str
    split: str
    seeds: int
    zero_shot: float
    zero_shot_sd: float
    final: float
    final_sd: float
    auc: float
    auc_sd: float
    #: see :func:`sample_efficiency`; ``None``: never reached scratch's final return
    efficiency: float | None
    budget: int

    def efficiency_text(self) -> str:
        if self.efficiency is None:
            return ">budget"
        return "inf (zero-shot)" if math.isinf(self.efficiency) else f"{self.efficiency:.2f}x"


def arm_metrics(task: str, arm: str, split: str, curves: list[tuple[np.ndarray, np.ndarray]],
                scratch: tuple[np.ndarray, np.ndarray] | None) -> ArmMetrics:
    """Metrics of one arm from its per-seed curves; ``scratch`` is scratch's seed-mean curve (or ``None``)."""
    zero = np.array([r[0] for _, r in curves])
    final = np.array([r[-1] for _, r in curves])
    auc = np.array([area_under_curve(s, r) for s, r in curves])
    steps, mean, _ = mean_curve(curves)
    efficiency = sample_efficiency(scratch, (steps, mean)) if scratch is not None and len(steps) else None
    return ArmMetrics(task, arm, split, len(curves), float(zero.mean()), float(zero.std()), float(final.mean()),
                      float(final.std()), float(auc.mean()), float(auc.std()), efficiency,
                      int(max(s[-1] for s, _ in curves)))
