"""Transfer metrics on synthetic curves with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from divmorph.pipeline.metrics import (
    EFFICIENCY_FRACTION,
    RobotCurves,
    area_under_curve,
    final_level,
    level_for,
    mean_curve,
    paired_run_interval,
    robot_interval,
    run_interval,
    steps_to_hold,
    task_metrics_from_curves,
)

STEPS = np.arange(0, 1001, 10, dtype=float)


def run(*robot_curves: np.ndarray, steps: np.ndarray = STEPS) -> RobotCurves:
    """One seed's evaluations: one curve per robot."""
    return RobotCurves(steps, [f"robot-{i}" for i in range(len(robot_curves))], np.array(robot_curves, float))


def by_arm(metrics):
    return {m.arm: m for m in metrics}


def test_scratch_final_return_is_the_mean_of_its_last_tenth():
    # y = x: the evaluations at 900..1000 average 950
    assert final_level(STEPS, STEPS) == pytest.approx(950.0)


def test_steps_to_hold_a_level_count_from_the_last_crossing_and_need_the_end_above_it():
    assert steps_to_hold(STEPS, STEPS, 800.0) == pytest.approx(800.0)
    assert steps_to_hold(STEPS, 2 * STEPS, 950.0) == pytest.approx(475.0)  # interpolated between 470 and 480
    assert steps_to_hold(STEPS, np.full_like(STEPS, 5.0), 3.0) == 0.0  # held from the start
    falls = 1000 - STEPS  # starts at the level, ends below it
    assert steps_to_hold(STEPS, falls, 800.0) is None
    dips = np.where((STEPS > 200) & (STEPS < 600), 0.0, 1000.0)  # above, below, above again: counted from the return
    assert steps_to_hold(STEPS, dips, 800.0) == pytest.approx(590.0 + 10 * 0.8)


def test_the_level_is_a_fixed_fraction_from_scratchs_start_to_the_best_final_return():
    assert level_for({"scratch": 0.0, "a": 50.0}, {"scratch": 500.0, "a": 1000.0}) == pytest.approx(EFFICIENCY_FRACTION * 1000)
    assert level_for({"a": -20.0, "b": 0.0}, {"a": 80.0, "b": 30.0}, fraction=0.5) == pytest.approx(30.0)  # no scratch: the lowest start
    assert level_for({"scratch": 10.0}, {"scratch": 5.0}) is None  # nothing was learnt


def test_an_arm_twice_as_fast_is_twice_as_sample_efficient():
    # level 0.8 x 1000 = 800: scratch (y = x) holds it from 800, the arm (y = 2x, capped) from 400
    metrics = by_arm(task_metrics_from_curves("Escape", "train", {"scratch": [run(STEPS)], "fast": [run(np.minimum(2 * STEPS, 1000))]}))
    assert metrics["fast"].level == pytest.approx(800.0)
    assert metrics["fast"].steps_to_level == pytest.approx(400.0) and metrics["scratch"].steps_to_level == pytest.approx(800.0)
    assert metrics["fast"].efficiency == pytest.approx(2.0) and metrics["fast"].efficiency_text() == "2.00x"
    assert metrics["scratch"].efficiency == pytest.approx(1.0)


def test_an_arm_that_starts_high_and_falls_gets_no_speed_up():
    """The former ratio credited "inf (zero-shot)" to any arm starting above scratch's final level,
    whatever it did next; an arm must end at the level to be credited with reaching it."""
    curves = {"scratch": [run(0.5 * STEPS)], "falls": [run(900 - 0.6 * STEPS)], "learns": [run(STEPS)]}
    metrics = by_arm(task_metrics_from_curves("Exploration", "train", curves))
    assert metrics["falls"].zero_shot == pytest.approx(900.0) and metrics["falls"].final == pytest.approx(300.0)
    assert metrics["falls"].steps_to_level is None and metrics["falls"].efficiency is None
    assert metrics["falls"].efficiency_text() == "-" and metrics["falls"].steps_text().startswith("not held")
    # scratch never holds 800: the arm that does gets a stated lower bound, not infinity
    assert metrics["learns"].efficiency == pytest.approx(1000 / 800) and metrics["learns"].efficiency_bound
    assert metrics["learns"].efficiency_text().startswith(">= 1.25x")
    # only an arm that holds the level from step 0 on is "from the start", and it says so
    start = by_arm(task_metrics_from_curves("Exploration", "train", {"scratch": [run(STEPS)], "zero": [run(np.full_like(STEPS, 1000.0))]}))
    assert math.isinf(start["zero"].efficiency) and start["zero"].efficiency_text() == "from the start (zero-shot)"


def test_area_under_the_curve_is_the_mean_return_over_training():
    assert area_under_curve(STEPS, STEPS) == pytest.approx(500.0)
    assert area_under_curve(STEPS, np.full_like(STEPS, 3.0)) == pytest.approx(3.0)


def test_metrics_are_means_over_seeds_and_robots_with_bootstrap_intervals():
    seeds = [run(2 * STEPS + 10, 2 * STEPS + 30), run(2 * STEPS - 30, 2 * STEPS - 10)]  # seed means +-20, robots +-10 around 2x
    m = by_arm(task_metrics_from_curves("Escape", "train", {"divmorph": seeds}))["divmorph"]
    assert (m.seeds, m.robots, m.budget) == (2, 2, 1000)
    assert (m.zero_shot, m.zero_shot_sd) == pytest.approx((0.0, 20.0))
    assert (m.final, m.final_sd) == pytest.approx((2000.0, 20.0))
    assert m.auc == pytest.approx(1000.0)
    for value, lo, hi in ((m.zero_shot, m.zero_shot_lo, m.zero_shot_hi), (m.final, m.final_lo, m.final_hi), (m.auc, m.auc_lo, m.auc_hi)):
        # resampling 2 seeds and 2 robots: the mean of a draw lies within +-30 of the point, and the interval is not a point
        assert value - 30 - 1e-9 <= lo < value < hi <= value + 30 + 1e-9
    # identical robots and seeds: nothing to resample, the interval is the point
    same = by_arm(task_metrics_from_curves("Escape", "train", {"x": [run(STEPS, STEPS), run(STEPS, STEPS)]}))["x"]
    assert same.final_lo == same.final == same.final_hi == 1000.0
    # the interval grows with the robots' spread
    narrow = by_arm(task_metrics_from_curves("E", "train", {"x": [run(STEPS + d) for d in (-1, 1)]}))["x"]
    wide = by_arm(task_metrics_from_curves("E", "train", {"x": [run(*(STEPS + d for d in (-50, -20, 20, 50)))]}))["x"]
    assert wide.final_hi - wide.final_lo > 10 * (narrow.final_hi - narrow.final_lo) > 0


def race(seed_means: tuple[float, ...], robots: int = 20, noise: float = 0.5, seed: int = 0) -> np.ndarray:
    """A made-up race: one value per (training run, robot), each run's robots scattered around its own mean."""
    rng = np.random.default_rng(seed)
    return np.asarray(seed_means, float)[:, None] + rng.normal(0, noise, (len(seed_means), robots))


def test_an_interval_over_training_runs_spans_runs_that_disagree():
    values = race((0.0, 5.0, 10.0))
    lo, hi = run_interval(values)
    # three runs: a draw can take the lowest (or the highest) run three times, and does in more than 2.5% of draws
    assert lo < 2 and hi > 8, (lo, hi)
    # the same 60 values taken as independent robots: the runs' disagreement is hidden
    flat_lo, flat_hi = robot_interval(values.ravel())
    assert flat_lo > 3 and flat_hi < 7, (flat_lo, flat_hi)


def test_an_interval_over_training_runs_is_narrow_when_runs_agree():
    lo, hi = run_interval(race((5.0, 5.0, 5.0)))
    assert 4.5 < lo < 5 < hi < 5.5, (lo, hi)
    # one run: robots only, as over per-robot values
    single = race((5.0,))
    assert run_interval(single) == robot_interval(single[0])


def test_a_paired_interval_resamples_each_arms_runs_and_pairs_robots():
    rng = np.random.default_rng(1)
    robots = rng.normal(0, 50, 20)  # robots differ far more than the arms do: pairing cancels it
    comparator = robots + race((0.0, 0.0, 0.0), noise=0.1, seed=2)
    lo, hi = paired_run_interval(robots + race((2.0, 2.0, 2.0), noise=0.1, seed=3), comparator)
    assert 1.5 < lo < 2 < hi < 2.5, (lo, hi)
    # the arm's runs disagree: its interval spans them, as an unpaired one does
    lo, hi = paired_run_interval(robots + race((0.0, 5.0, 10.0), seed=3), comparator)
    assert lo < 2 and hi > 8, (lo, hi)
    # a fixed comparator (one row, e.g. a many-draw start) against runs that agree
    lo, hi = paired_run_interval(robots + race((2.0, 2.0, 2.0), noise=0.1, seed=3), robots[None, :])
    assert 1.5 < lo < 2 < hi < 2.5, (lo, hi)
    with pytest.raises(ValueError, match="robots"):
        paired_run_interval(race((0.0, 1.0)), race((0.0, 1.0), robots=19))
    with pytest.raises(ValueError, match="missing"):
        run_interval(np.array([[1.0, np.nan], [2.0, 3.0]]))


def test_episodes_are_averaged_per_robot_and_seeds_share_steps_and_robots():
    rows = [
        {"timesteps": t, "split": "train", "robot": r, "episode": e, "return": 10 * e + (100 if r == "b" else 0) + t}
        for t in (0, 50, 100)
        for r in ("a", "b")
        for e in range(3)
    ]
    curves = RobotCurves.from_rows(rows + [{"timesteps": 0, "split": "novel", "robot": "c", "episode": 0, "return": -1}], "train")
    assert curves.robots == ["a", "b"] and list(curves.steps) == [0, 50, 100]
    np.testing.assert_allclose(curves.values, [[10, 60, 110], [110, 160, 210]])
    # a step some robot lacks (a killed evaluation) is left out
    partial = RobotCurves.from_rows(rows + [{"timesteps": 150, "split": "train", "robot": "a", "episode": 0, "return": 0}], "train")
    assert list(partial.steps) == [0, 50, 100]
    steps, mean, sd = mean_curve([curves.mean(), (curves.steps, curves.mean()[1] + 20)])
    assert np.allclose(mean, curves.mean()[1] + 10) and np.allclose(sd, 10.0)


def test_seeds_evaluated_at_different_steps_are_compared_over_their_whole_curves():
    """Resumed runs evaluate at the checkpoint and every eval_every from it, so seeds' steps drift apart
    (here they share step 0 alone); the metrics must still read every seed's whole curve."""
    every_100 = np.array([0, 100, 200, 300, 400, 500, 502], float)
    resumed = np.array([0, 100, 200, 250, 350, 450, 501], float)  # resumed at 150, evaluated there and every 100 on
    seeds = [run(every_100, steps=every_100), run(resumed, steps=resumed + np.array([0, 50, 0, 0, 0, 0, 0]))]
    m = by_arm(task_metrics_from_curves("Escape", "train", {"scratch": seeds}))["scratch"]
    assert m.seeds == 2
    assert m.final > 400, f"the final return is the curves' end, not their shared step 0: {m.final}"
    assert m.auc == pytest.approx(250, rel=0.05), "the mean return over training: a line from 0 to ~500"
    steps, mean, _ = mean_curve([(s.steps, s.values[0]) for s in seeds])
    assert steps[0] == 0 and steps[-1] == 501 and len(steps) > 2, steps
    np.testing.assert_allclose(mean[[0, -1]], [0, 501])


def test_metrics_leave_out_a_seed_whose_run_is_still_going(tmp_path):
    """A run in progress has a shorter curve; counted, it would cut every seed's curve to its last step."""
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.curves import task_metrics, write_eval
    from divmorph.pipeline.files import mark_done

    def write(seed: int, steps: tuple[int, ...], done: bool) -> None:
        folder = tmp_path / "transfer" / "Escape" / "scratch" / f"seed-{seed}"
        rows = [
            {"timesteps": t, "split": split, "robot": "train-000", "episode": 0, "return": float(t), "length": 10}
            for t in steps
            for split in ("train", "novel")
        ]
        write_eval(folder / "eval.csv", rows)
        if done:
            mark_done(folder)

    write(0, (0, 100, 200), done=True)
    write(1, (0,), done=False)
    (metrics,) = [m for m in task_metrics(load_profile("demo"), tmp_path, "Escape") if m.split == "train"]
    assert metrics.seeds == 1, "the unfinished seed is not counted"
    assert metrics.final > 100, f"the finished seed's final return, not its step-0 return: {metrics.final}"


def test_each_robot_and_evaluation_seed_draws_its_own_episodes():
    """On a task with random goals, the robots of one evaluation walk to different goals, two
    evaluation seeds share no goal, and the same seed gives the same goals again (with ``seed + e``
    every robot of an evaluation got the same few goals, and seed 0's episode 1 was seed 1's episode 0)."""
    from divmorph.pipeline.curves import robot_venv
    from unimal_envs.morphology import morphology_files

    robots = morphology_files("train")[:3]

    def goals(seed: int, episodes: int = 2) -> list[tuple[float, float]]:
        venv = robot_venv("Unimal-PointNav-v0", robots, 5, seed)
        found = []
        for _ in range(episodes):
            venv.reset()  # every robot's next episode
            found += [tuple(np.round(env.unwrapped.task.goal[:2], 6)) for env in venv.envs]
        venv.close()
        return found

    first, second = goals(0), goals(1)
    assert len(set(first + second)) == len(first) + len(second)
    assert goals(0) == first
