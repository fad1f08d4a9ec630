"""The setting ladder's reading (``results/transfer-setting/read.py``) follows its rule: an arm rises when its
last evaluation minus its start has a run-resampled interval wholly above 0."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from divmorph.pipeline.curves import write_eval

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "results" / "transfer-setting"


def load_reader():
    spec = importlib.util.spec_from_file_location("transfer_setting_read", STUDY / "read.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def made_up_setting(folder: Path, closest_gain: float, scratch_gains: list[float]) -> Path:
    """A setting whose runs' training robots all move by the given gains (one per scratch seed), with noise."""
    rng = np.random.default_rng(0)
    robots = [f"robot-{i}" for i in range(8)]
    setting = folder / "S1"
    runs = {("closest", seed): closest_gain for seed in range(3)} | {("scratch", s): g for s, g in enumerate(scratch_gains)}
    for (arm, seed), gain in runs.items():
        run = setting / "runs" / "transfer" / "ManipulateBox" / arm / f"seed-{seed}"
        run.mkdir(parents=True)
        start = 100.0 if arm == "closest" else 0.0
        rows = [
            {
                "timesteps": step,
                "split": "train",
                "robot": robot,
                "episode": 0,
                "return": start + gain * step + rng.normal(0, 1),
                "length": 10,
            }
            for step in (0, 1)
            for robot in robots
        ]
        write_eval(run / "eval.csv", rows)
        (run / "done.json").write_text("{}")
    start = {"closest": {str(seed): {robot: 100.0 + rng.normal(0, 1) for robot in robots} for seed in range(5)}}
    (setting / "baseline.json").write_text(json.dumps(start))
    return setting


@pytest.mark.parametrize("closest_gain, expected", [(0.0, "no"), (20.0, "yes")])
def test_an_arm_rises_only_when_it_climbs_beyond_noise(tmp_path, closest_gain, expected):
    reader = load_reader()
    rows = {row["arm"]: row for row in reader.read_setting(made_up_setting(tmp_path, closest_gain, [30.0, 30.0, 30.0]))}
    assert rows[reader.ARMS["closest"]]["rises"] == expected
    assert rows[reader.ARMS["scratch"]]["rises"] == "yes"


def test_seeds_that_disagree_do_not_rise(tmp_path):
    """Two scratch runs climb, one falls further: the interval resamples runs, so it spans 0 although the
    mean climbs (broken once: rising on a positive mean -> fails)."""
    reader = load_reader()
    rows = {row["arm"]: row for row in reader.read_setting(made_up_setting(tmp_path, 0.0, [40.0, 40.0, -60.0]))}
    assert rows[reader.ARMS["scratch"]]["rises"] == "no"


@pytest.mark.shipped_results
def test_the_shipped_reading_is_what_the_packed_runs_read_to(tmp_path):
    reader = load_reader()
    text = reader.main(["--out", str(tmp_path)])
    assert (STUDY / "reading.md").read_text() == text + "\n"
    assert (tmp_path / "curves.png").stat().st_size > 0
