"""Shipped models run on the robots they were trained on, by default, wherever a model folder is accepted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from divmorph.pipeline.config import ConfigError
from divmorph.pipeline.robots import trained_robot_set, trained_robots

RUN = Path(__file__).resolve().parents[1] / "results" / "cpu"
RUN100 = RUN.parent / "cpu100"
#: the cpu100 Obstacle teacher's best training robot (results/cpu100/checks/teacher-Obstacle)
CLIMBER = "mvt-5506-1-12-17-11-10-12"


def test_a_model_folder_names_the_robots_of_its_run(tmp_path):
    run = tmp_path / "run"
    (run / "teachers" / "FT").mkdir(parents=True)
    (run / "robot_sets.json").write_text(json.dumps({"train": {"set": "train", "robots": ["train-004", "train-001"]}}))
    robots = trained_robots(run / "teachers" / "FT" / "model.zip")
    assert [r.stem for r in robots] == ["train-004", "train-001"] and all(r.is_file() for r in robots)
    assert trained_robot_set(run / "teachers" / "FT") == "train"
    assert trained_robots(tmp_path) is None  # no run record: the caller falls back to its default
    (run / "robot_sets.json").write_text(json.dumps({"train": {"set": "train", "robots": ["train-999"]}}))
    with pytest.raises(ConfigError, match="train-999"):
        trained_robots(run / "teachers" / "FT")


@pytest.mark.shipped_results
def test_the_shipped_teachers_default_to_the_official_robots(official_cache, archived_study):
    robots = trained_robots(RUN100 / "teachers" / "Obstacle")
    assert len(robots) == 100 and robots[0].stem == "floor-1409-0-12-01-12-30-07"
    assert trained_robot_set(archived_study("results/cpu") / "student") == "unimals100-train"  # the small run, archived


@pytest.mark.shipped_results
def test_the_load_example_runs_the_shipped_teacher_on_its_robot_with_no_env_flags(official_cache, capsys):
    """The example finds the robot among the run's training robots and builds the env the run trained
    with (heights above the ground): the Obstacle teacher gets far over solid blocks (1941 when the
    run was recorded, 809 on the host of 2026-11-28 -- a 1,000-step episode is chaotic, so the last bits of
    another CPU's floating point send it elsewhere; about -2 without its observation statistics)."""
    import runpy
    import sys

    argv = sys.argv
    sys.argv = ["load_run_model.py", str(RUN100 / "teachers" / "Obstacle"), "--robot", CLIMBER, "--seed", "1", "--steps", "1000"]
    try:
        runpy.run_path(str(RUN.parents[1] / "examples" / "load_run_model.py"), run_name="__main__")
    finally:
        sys.argv = argv
    out = capsys.readouterr().out
    ret = float(out.split(f"{CLIMBER}, episode 0: return")[1].split()[0])
    assert ret > 300, out  # far from the -2 of a model fed unnormalised observations, on any host


@pytest.mark.shipped_results
def test_the_small_runs_compact_actors_name_their_robot_set(archived_study):
    onnx = pytest.importorskip("onnx")
    actors = sorted((archived_study("results/cpu") / "export").glob("*-FT/actor.onnx"))
    assert len(actors) == 4
    for path in actors:
        props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
        assert props["robot_set"] == "unimals100-train" and props["robot"] in path.parent.name
