"""The recorded runs' models (``results/cpu100``, the 100-robot run, and ``results/cpu``, the small run)
load on a fresh clone and do what the runs say.

Only the models' robots are external: the official unimals_100 training set, read from ``../shared``
(skipped cleanly without it).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph import MetaMorphPolicy
from sb3_divmorph.algos.hyperdistill_fit import load_student
from divmorph.pipeline.config import load_profile
from divmorph.pipeline.evaluate import evaluate_model, evaluation_plan
from divmorph.pipeline.robots import trained_env_kwargs
from divmorph.pipeline.training import stage_model, stage_normalizer
from unimal_envs.instructions import shipped_embeddings

RESULTS = Path(__file__).resolve().parents[1] / "results"
#: every test here reads the shipped runs: the results suite (`make test-results`), not the library's
pytestmark = pytest.mark.shipped_results
#: the small run: its raw files (records, statistics, exports) are archived (``tools/archive_runs.py``)
SMALL_RUN = "results/cpu"
RUN100 = RESULTS / "cpu100"
#: the 100-robot run's teachers, all shipped
TEACHERS100 = ["FT", "VT", "Incline", "Obstacle", "Patrol"]
#: the cpu100 Obstacle teacher's best training robot (return 2254 in results/cpu100/checks/teacher-Obstacle)
CLIMBER = "mvt-5506-1-12-17-11-10-12"
#: the cpu100 FT teacher's best training robot (return 2336 in results/cpu100/checks/teacher-FT)
WALKER = "mvt-5506-12-4-17-12-01-27"


@pytest.mark.parametrize("task", TEACHERS100)
def test_every_teacher_loads_with_its_normaliser(task):
    folder = RUN100 / "teachers" / task
    model = PPO.load(stage_model(folder), device="cpu")
    assert isinstance(model.policy, MetaMorphPolicy)
    statistics = stage_normalizer(folder)
    assert statistics is not None and statistics.is_file()
    with open(statistics, "rb") as f:
        normalizer = pickle.load(f)
    assert isinstance(normalizer, VecNormalize) and normalizer.obs_rms["proprioceptive"].count > 1e6


def test_the_ft_teacher_walks_on_a_fresh_clone(official_train):
    """On its best training robot the FT teacher walks the whole episode far forward (1780-2531 on
    seeds 0-2 when the run was recorded; an untrained policy gets ~0)."""
    rows = evaluate_model(RUN100 / "teachers" / "FT", "FT", [official_train / "xml" / f"{WALKER}.xml"], 1, 1000, 0)
    assert rows[0]["length"] == 1000 and rows[0]["return"] > 1000


def test_the_obstacle_teacher_gets_past_its_blocks_on_a_fresh_clone(official_train):
    """Blocks are solid (a robot that walks into one stops), and each seed lays them out anew: on its
    best training robot the teacher's mean return over three layouts is far above the untrained
    policy's ~0 (it reached 341-1941 on these seeds when the run was recorded)."""
    robot = official_train / "xml" / f"{CLIMBER}.xml"
    # no env arguments: the model's run says which observations it learnt on (heights above the ground)
    returns = [evaluate_model(RUN100 / "teachers" / "Obstacle", "Obstacle", [robot], 1, 1000, seed)[0]["return"] for seed in (1, 2, 3)]
    assert sum(returns) / 3 > 400, returns


@pytest.mark.parametrize(
    "folder, policy",
    [
        ("student", "DivMorphPolicy"),
        ("students/distilled", "MetaMorphPolicy"),
        ("students/deploy-g1k1", "DivMorphPolicy"),
    ],
)
def test_the_students_load_with_their_normalisers(folder, policy):
    model = PPO.load(stage_model(RUN100 / folder), device="cpu")
    assert type(model.policy).__name__ == policy
    assert stage_normalizer(RUN100 / folder) is not None


def test_the_student_acts_on_its_instruction(official_train):
    """One DivMorph student serves five tasks: on the same robot and state, the FT instruction and the
    VT one give different actions (its task gates read the instruction's embedding)."""
    folder = RUN100 / "student"
    model = PPO.load(stage_model(folder), device="cpu")
    with open(stage_normalizer(folder), "rb") as f:
        normalizer = pickle.load(f)
    env = gym.make("Unimal-FT-v0", morphologies=[official_train / "xml" / f"{WALKER}.xml"], **trained_env_kwargs(folder))
    obs, _ = env.reset(seed=0)
    batch = {k: np.asarray(v)[None] for k, v in obs.items()}
    actions = {}
    for task in ("FT", "VT"):
        batch["task_embedding"] = shipped_embeddings()[task][None].astype(np.float32)
        actions[task] = model.predict(normalizer.normalize_obs(dict(batch)), deterministic=True)[0]
    env.close()
    assert np.abs(actions["FT"] - actions["VT"]).max() > 0.05


def test_the_student_walks_like_its_teacher_on_a_fresh_clone(official_train):
    """The DivMorph student, one policy for five tasks, walks the FT teacher's best training robot the
    whole episode far forward (1451-2136 on seeds 0-2 when the run was recorded; the teacher 1780-2531)."""
    rows = evaluate_model(RUN100 / "student", "FT", [official_train / "xml" / f"{WALKER}.xml"], 1, 1000, 0)
    assert rows[0]["length"] == 1000 and rows[0]["return"] > 1000


def test_the_hyperdistill_student_walks_on_its_teachers_statistics(official_train):
    """The HyperDistill baseline ships without a normaliser of its own: it holds each task's teacher's
    statistics, and its generated MLP walks the FT teacher's best robot (1067 when the run was recorded)."""
    folder = RUN100 / "hyperdistill" / "student"
    student = load_student(stage_model(folder))
    assert stage_normalizer(folder) is None and student.observation_statistics == "teachers"
    assert student.teacher_set.sum() == len(TEACHERS100)
    rows = evaluate_model(folder, "FT", [official_train / "xml" / f"{WALKER}.xml"], 1, 1000, 0)
    assert rows[0]["length"] == 1000 and rows[0]["return"] > 600


@pytest.mark.parametrize(
    "folder",
    [
        "teachers/FT",
        "teachers/Obstacle",
        "student",
        "students/distilled",
        "students/deploy-g1k1",
        "hyperdistill/student",
        "students/no-kdiv-transformer",
        "students/no-kdiv-decoder",
        "students/no-orthogonality",
    ],
)
def test_a_model_that_does_not_ship_is_named_with_the_way_back(folder, capsys, archived_study):
    """These finished models live in git history only (tracked-size limit): loading one says so and how
    to restore it, and evaluating the whole run skips it with a note instead of failing."""
    RUN = archived_study(SMALL_RUN)
    with pytest.raises(FileNotFoundError, match="not in this checkout.*git checkout"):
        stage_model(RUN / folder)
    plan = evaluation_plan(load_profile("cpu"), RUN)
    assert RUN / folder not in {path for _, path, _ in plan}
    assert f"skipping {RUN / folder}" in capsys.readouterr().out


def test_the_small_runs_compact_actors_are_archived_as_onnx(archived_study):
    """The DivMorph student's four FT actors are kept as ONNX; the other 36 exports keep their reports (results/cpu/README.md
    says how to make their files, and the four's TorchScript, again)."""
    RUN = archived_study(SMALL_RUN)
    exports = sorted((RUN / "export").glob("*-FT"))
    assert len(exports) == 4 and all((e / "actor.onnx").is_file() for e in exports)
    reports = sorted((RUN / "export").glob("**/report.json"))
    assert len(reports) == 40 and all((r.parent / "done.json").is_file() for r in reports)
