"""Transfer metrics on synthetic curves with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_divmorph.pipeline.metrics import (
    area_under_curve,
    arm_metrics,
    final_level,
    mean_curve,
    sample_efficiency,
    steps_to_reach,
)

STEPS = np.arange(0, 1001, 10, dtype=float)


def test_scratch_final_return_is_the_mean_of_its_last_tenth():
    # y = x: the evaluations at 900..1000 average 950
    assert final_level(STEPS, STEPS) == pytest.approx(950.0)


def test_an_arm_twice_as_fast_is_twice_as_sample_efficient():
    # scratch y = x reaches 950 at 950; the arm y = 2x reaches it at 475 (interpolated between 470 and 480)
    assert steps_to_reach(STEPS, 2 * STEPS, 950.0) == pytest.approx(475.0)
    assert sample_efficiency((STEPS, STEPS), (STEPS, 2 * STEPS)) == pytest.approx(2.0)
    # four times as fast, on coarser evaluations
    coarse = np.arange(0, 1001, 50, dtype=float)
    assert sample_efficiency((STEPS, STEPS), (coarse, 4 * coarse)) == pytest.approx(4.0)
    # slower arms are below 1
    assert sample_efficiency((STEPS, STEPS), (STEPS, np.minimum(STEPS * 0.5 + 500, 1000))) == pytest.approx(950 / 900)


def test_never_reaching_is_over_budget_and_starting_there_is_infinite():
    assert sample_efficiency((STEPS, STEPS), (STEPS, 0.5 * STEPS)) is None
    assert sample_efficiency((STEPS, STEPS), (STEPS, np.full_like(STEPS, 960.0))) == math.inf


def test_area_under_the_curve_is_the_mean_return_over_training():
    assert area_under_curve(STEPS, STEPS) == pytest.approx(500.0)
    assert area_under_curve(STEPS, np.full_like(STEPS, 3.0)) == pytest.approx(3.0)


def test_arm_metrics_pool_seeds_as_mean_and_sd():
    seeds = [(STEPS, 2 * STEPS + 10), (STEPS, 2 * STEPS - 10)]
    scratch = (STEPS, STEPS)
    m = arm_metrics("Escape", "divmorph", "train", seeds, scratch)
    assert (m.zero_shot, m.zero_shot_sd) == pytest.approx((0.0, 10.0))
    assert (m.final, m.final_sd) == pytest.approx((2000.0, 10.0))
    assert m.efficiency == pytest.approx(2.0) and m.efficiency_text() == "2.00x"
    assert m.budget == 1000 and m.seeds == 2
    steps, mean, sd = mean_curve(seeds)
    assert np.allclose(mean, 2 * STEPS) and np.allclose(sd, 10.0)
    never = arm_metrics("Escape", "grl", "novel", [(STEPS, 0 * STEPS)], scratch)
    assert never.efficiency is None and never.efficiency_text() == ">budget"
