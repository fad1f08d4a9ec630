"""The divmorph pipeline end to end on a tiny profile: stages, resumption, atomicity, bad input."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import importlib.util

import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3 import PPO

from divmorph.cli import main as cli
from divmorph.pipeline.arms import ARMS
from divmorph.pipeline.config import ConfigError, load_profile, load_profiles, load_zoo_entry
from divmorph.pipeline.files import read_done
from divmorph.pipeline.training import latest_checkpoint
from sb3_divmorph.policies import DivMorphPolicy, MetaMorphPolicy
import unimal_envs
from unimal_envs.morphology.loader import morphology_files

REPO = Path(__file__).resolve().parents[1]
TINY_POLICY = {"d_model": 16, "n_layers": 1, "ff_dim": 32, "exteroception": {"hfield": [8], "goal": [4], "object": [4]}}
TINY = {
    "seed": 0,
    "device": "cpu",
    "torch_threads": 1,
    "train_robots": 2,
    "novel_robots": 2,
    "max_episode_steps": 40,
    "teachers": {
        "tasks": ["FT", "Patrol"],
        "hyperparams": str(REPO / "zoo_configs" / "ppo.yml"),
        "n_timesteps": 128,
        "overrides": {"n_envs": 1, "n_steps": 64, "batch_size": 64, "n_epochs": 1},
        # as in the shipped profiles, each teacher's exteroception follows its task's zoo entry (FT: none)
        "policy_kwargs": {k: v for k, v in TINY_POLICY.items() if k != "exteroception"},
        "checkpoint_every": 64,
    },
    "student": {"policy_kwargs": {**TINY_POLICY, "n_morph_tailors": 6, "n_task_tailors": 6, "top_k_morph": 2, "top_k_task": 2}},
    "distill": {"n_timesteps": 128, "n_envs": 2, "n_steps": 32, "epochs": 1, "batch_size": 32, "buffer_size": 256, "checkpoint_every": 64},
    "transfer": {
        "tasks": ["Escape"],
        "n_timesteps": 128,
        "overrides": {"n_envs": 1, "n_steps": 64, "batch_size": 64, "n_epochs": 1},
        "checkpoint_every": 64,
        "arms": list(ARMS),
        "seeds": [0],
        "eval_every": 64,
        "eval_episodes": 1,
    },
    "hyperdistill": {
        "teacher_policy": "MetaMorphPolicy",
        "policy_kwargs": {"hidden_dim": 16, "embed_dim": 8},
        "rollout_samples": 256,
        "epochs": 2,
        "batch_size": 64,
        "n_envs": 2,
    },
    "grl": {"population": 2, "generations": 2, "steps_per_agent": 64, "learngene_layers": 2, "tournament": 2, "mutation": 0.5},
    "export": {"tasks": ["FT", "Escape"], "latency_repeats": 5},
    "evaluate": {"episodes": 1},
}


def write_profiles(folder: Path, **changes) -> Path:
    profile = json.loads(json.dumps(TINY))
    for dotted, value in changes.items():
        *parents, key = dotted.split("__")
        target = profile
        for parent in parents:
            target = target[parent]
        target[key] = value
    path = folder / "profiles.yml"
    path.write_text(yaml.safe_dump({"tiny": profile}))
    return path


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """The whole tiny pipeline, run once through the CLI."""
    folder = tmp_path_factory.mktemp("pipeline")
    profiles = write_profiles(folder)
    out = folder / "run"
    assert cli(["pipeline", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]) == 0
    th.set_num_threads(2)
    return out, profiles


def test_every_stage_writes_its_outputs(finished_run):
    out, _ = finished_run
    for task in ("FT", "Patrol"):
        assert (out / "teachers" / task / "model.zip").is_file() and (out / "teachers" / task / "vecnormalize.pkl").is_file()
        assert read_done(out / "teachers" / task)["num_timesteps"] >= 128
    with open(next((out / "student" / "logs").glob("run-*/progress.csv"))) as f:
        columns = next(csv.reader(f))
    assert {"distill/loss", "distill/kl/FT", "distill/kl/Patrol", "gates/task_entropy", "distill/beta"} <= set(columns)
    assert list((out / "student" / "logs").glob("run-*/events.out.tfevents*"))
    for arm in ARMS:
        assert read_done(out / "transfer" / "Escape" / arm / "seed-0")["num_timesteps"] >= 128
    reports = sorted((out / "export").glob("*/report.json"))
    assert len(reports) == 4  # 2 robots (one per split) x 2 tasks
    for path in reports:
        report = json.loads(path.read_text())
        assert report["max_abs_diff"] <= 1e-5
        assert report["compact_weights"] < report["student_actor_parameters"]
        assert (path.parent / "actor.pt").is_file()
        # the deployed actor's own episode does what the student's does
        assert report["compact_episode_length"] == report["student_episode_length"] > 0
        assert report["compact_return"] == pytest.approx(report["student_return"], rel=1e-3, abs=1e-3)
    with open(out / "evaluate" / "returns.csv") as f:
        rows = list(csv.DictReader(f))
    # teachers and their untrained twins (2 tasks each) + student (2 train + 1 novel task) + the arms' 4 other
    # students (2 training tasks each) + HyperDistill (2) + 9 transfer arms, on 2 + 2 robots
    assert len(rows) == (2 + 2 + 3 + 4 * 2 + 2 + len(ARMS)) * 4
    assert {r["model"] for r in rows} >= {"teacher-untrained", "student-distilled", "student-no-orthogonality"}
    assert {r["split"] for r in rows} == {"train", "novel"}
    assert all(np.isfinite(float(r["return"])) for r in rows)
    with np.load(out / "evaluate" / "gates.npz") as gates:
        assert gates["task_gates"].shape == (10, 6) and gates["morphology_gates"].shape == (4, 6)
    for png in ("curves.png", "figures/gates.png", "returns.png"):
        assert (out / "report" / png).stat().st_size > 10_000
    assert not (out / "report" / "gates.png").exists()  # one gates figure, not a copy beside figures/
    summary = (out / "summary.md").read_text()
    assert "Deployment" in summary and "transfer-divmorph" in summary and "Transfer metrics" in summary
    assert "## Findings" in summary and "| FT | " in summary


def test_an_untrained_teacher_is_the_teacher_runs_initial_policy(finished_run):
    from stable_baselines3 import PPO

    from divmorph.pipeline.teachers import teacher_run

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)
    initial = teacher_run(profile, out, "FT", progress_bar=False).make_model()
    trained = PPO.load(out / "teachers" / "FT" / "model.zip", device="cpu")
    again = teacher_run(profile, out, "FT", progress_bar=False).make_model()
    first = {k: v.clone() for k, v in initial.policy.state_dict().items()}
    assert all(th.equal(first[k], v) for k, v in again.policy.state_dict().items())  # same seed, same weights
    assert any(not th.equal(first[k], v) for k, v in trained.policy.state_dict().items())  # training moved them


def test_the_evaluation_reuses_a_transfer_runs_final_evaluation_only_when_it_is_the_same(finished_run):
    from divmorph.pipeline.evaluate import evaluate_model, final_evaluation
    from divmorph.pipeline.robots import profile_robots

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)
    robots = profile_robots(profile, "novel")
    folder = out / "transfer" / "Escape" / "scratch" / "seed-0"
    reused = final_evaluation(folder, "novel", robots, 1)
    rolled = evaluate_model(folder, "Escape", robots, 1, profile.max_episode_steps, profile.seed)
    key = lambda row: (row["morphology"], row["episode"])  # noqa: E731
    assert [(key(r), r["length"]) for r in sorted(reused, key=key)] == [(key(r), r["length"]) for r in sorted(rolled, key=key)]
    assert [r["return"] for r in sorted(reused, key=key)] == pytest.approx([r["return"] for r in sorted(rolled, key=key)], rel=1e-5)
    assert final_evaluation(folder, "novel", robots, 2) is None  # other episodes: rolled out anew
    assert final_evaluation(folder, "novel", robots[:1], 1) is None


def test_an_evaluation_samples_actions_only_when_asked(finished_run):
    """``deterministic=False`` rolls out sampled actions (as in training): other returns from the same
    seed; the default repeats itself."""
    from divmorph.pipeline.evaluate import evaluate_model
    from divmorph.pipeline.robots import profile_robots

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)
    robots = profile_robots(profile, "train")
    folder = out / "teachers" / "FT"
    roll = lambda **kw: [r["return"] for r in evaluate_model(folder, "FT", robots, 1, 50, profile.seed, **kw)]  # noqa: E731
    assert roll() == roll()
    assert roll(deterministic=False) != pytest.approx(roll(), abs=1e-6)


def test_two_parts_and_a_merge_give_the_whole_evaluation(finished_run, tmp_path):
    """``evaluate --part 1/2`` and ``--part 2/2`` (one process per core) take disjoint shares; the plain
    evaluation afterwards merges them, rolls nothing out again, and writes what one process would."""
    out, profiles = copied_run(finished_run, tmp_path)
    whole = read_returns(out / "evaluate" / "returns.csv")
    (out / "evaluate" / "returns.csv").unlink()
    (out / "evaluate" / "done.json").unlink()
    base = ["evaluate", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli([*base, "--part", "1/2"]) == 0 and cli([*base, "--part", "2/2"]) == 0
    shares = [{key[:3] for key in read_returns(out / "evaluate" / "parts" / f"part-{k}-of-2.csv")} for k in (1, 2)]
    assert shares[0] and shares[1] and not shares[0] & shares[1]
    # part 1's rows are kept as written (one marked to tell); part 2 "lost": the merge evaluates its share again
    part_1 = out / "evaluate" / "parts" / "part-1-of-2.csv"
    lines = part_1.read_text().splitlines()
    marked = lines[1].split(",")
    lines[1] = ",".join([*marked[:5], "12345.0", *marked[6:]])
    part_1.write_text("\n".join(lines) + "\n")
    (out / "evaluate" / "parts" / "part-2-of-2.csv").write_text("model,task,split,morphology,episode,return,length\n")
    assert cli([*base]) == 0
    merged = read_returns(out / "evaluate" / "returns.csv")
    assert merged.pop(tuple(marked[:5])) == 12345.0
    assert merged == pytest.approx({k: v for k, v in whole.items() if k != tuple(marked[:5])}, rel=1e-5)
    assert not (out / "evaluate" / "parts").exists()
    with pytest.raises(SystemExit, match="2"):
        cli([*base, "--part", "3/2"])


def test_parts_of_a_finished_evaluation_merge_the_models_finished_after_it(finished_run, tmp_path):
    """A run evaluated once grows (a transfer seed finishes later): ``--part 1/2`` and ``--part 2/2``
    roll out only the new model, and the plain evaluation afterwards merges those rows into the
    finished ``returns.csv`` instead of calling the run already evaluated and dropping them."""
    out, profiles = copied_run(finished_run, tmp_path)
    returns = out / "evaluate" / "returns.csv"
    whole = read_returns(returns)
    assert (out / "evaluate" / "done.json").is_file()
    header, *lines = returns.read_text().splitlines()
    later = [line for line in lines if line.startswith("transfer-scratch,")]  # "finished after the evaluation"
    assert later
    returns.write_text("\n".join([header, *(line for line in lines if line not in later)]) + "\n")
    base = ["evaluate", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli([*base, "--part", "1/2"]) == 0 and cli([*base, "--part", "2/2"]) == 0
    parted = {key for k in (1, 2) for key in read_returns(out / "evaluate" / "parts" / f"part-{k}-of-2.csv")}
    assert {key for key in whole if key[0] == "transfer-scratch"} <= parted
    assert cli([*base]) == 0
    assert read_returns(returns) == pytest.approx(whole, rel=1e-5)
    assert not (out / "evaluate" / "parts").exists()


def test_every_model_keeps_its_env_settings_beside_it(finished_run, tmp_path):
    """A stage writes ``env.json`` (robots and observation setting, read from its envs) beside its
    model, so a model folder copied out of its run still loads onto its own robots and settings."""
    import shutil

    from divmorph.pipeline.robots import profile_robots
    from divmorph.pretrained import load_pretrained

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)
    trained = [r.stem for r in profile_robots(profile, "train")]
    for folder in (out / "teachers" / "FT", out / "student", out / "transfer" / "Escape" / "divmorph" / "seed-0"):
        assert json.loads((folder / "env.json").read_text()) == {"height_reference": "world", "robots": trained}, folder
    copy = tmp_path / "FT"
    shutil.copytree(out / "teachers" / "FT", copy)
    (copy / "env.json").write_text(json.dumps({"height_reference": "ground", "robots": trained[::-1]}))
    model = load_pretrained(copy)  # no run records above it: env.json alone
    assert [r.stem for r in model.robots] == trained[::-1] and model.env_kwargs == {"height_reference": "ground"}


def test_an_out_of_distribution_set_is_evaluated_as_its_own_split(finished_run, tmp_path):
    """``ood_set`` adds the split ``ood``: every model is rolled out on its robots, except a transfer
    run that ships only its curves (no model) and has none on that split, which is left out rather
    than failing the evaluation."""
    out, profiles = copied_run(finished_run, tmp_path)
    (out / "transfer" / "Escape" / "scratch" / "seed-0" / "model.zip").unlink()  # a recorded run's curves only
    into = tmp_path / "ood"
    base = ["evaluate", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli([*base, "--set", "ood_set=novel", "--set", "ood_robots=2", "--split", "ood", "--into", str(into)]) == 0
    rows = list(csv.DictReader(open(into / "returns.csv")))
    assert {r["split"] for r in rows} == {"ood"} and {r["morphology"] for r in rows} == {"novel-000", "novel-001"}
    models = {r["model"] for r in rows}
    assert {"teacher", "student", "transfer-divmorph"} <= models and "transfer-scratch" not in models
    with pytest.raises(SystemExit, match="2"):
        cli([*base, "--split", "sideways", "--into", str(tmp_path / "x")])


def test_an_evaluation_keeps_each_transfer_seed_apart(tmp_path):
    """A transfer arm's seeds are separate jobs: one seed's complete rows never stand for the others'
    (an interrupted evaluation evaluates the missing seeds), and seeds pooled by an older file without
    the seed column are evaluated again rather than kept beside the new rows."""
    from divmorph.pipeline.evaluate import complete_rows, job_key, write_rows

    robots = [Path("a.xml"), Path("b.xml")]
    arm = tmp_path / "transfer" / "Escape" / "scratch"
    jobs = {job_key("transfer-scratch", arm / f"seed-{seed}", "Escape", "novel"): (robots, 2) for seed in (0, 1)}
    assert sorted(key[3] for key in jobs) == ["0", "1"]
    assert job_key("transfer-scratch", arm, "Escape", "novel")[3] == "0"  # a run begun before seeds existed
    assert job_key("teacher", tmp_path / "teachers" / "FT", "FT", "train")[3] == ""
    rows = [
        {
            "model": "transfer-scratch",
            "task": "Escape",
            "split": "novel",
            "seed": "0",
            "morphology": r.stem,
            "episode": e,
            "return": 1.0,
            "length": 5,
        }
        for r in robots
        for e in range(2)
    ]
    write_rows(tmp_path / "returns.csv", rows)
    kept = complete_rows([tmp_path / "returns.csv"], jobs)
    assert {row["seed"] for row in kept} == {"0"} and len(kept) == 4  # seed 1 is still to do
    pooled = [{**row, "seed": ""} for row in rows] * 2  # two seeds' rows under one key (an older file)
    write_rows(tmp_path / "returns.csv", pooled)
    assert complete_rows([tmp_path / "returns.csv"], jobs) == []
    other = [{**row, "model": "teacher", "task": "FT", "split": "train", "seed": ""} for row in rows]
    write_rows(tmp_path / "returns.csv", other)  # a model this checkout no longer has keeps its rows
    assert len(complete_rows([tmp_path / "returns.csv"], jobs)) == 4


def test_a_run_with_packed_logs_reads_and_reports_as_before(finished_run, tmp_path):
    """tools/pack_logs.py gzips a recorded run's finished logs; every reader gives the same numbers,
    the report the same tables, and a later plain file wins over its packed twin."""
    import importlib
    import runpy
    import sys

    from divmorph.pipeline.curves import read_eval
    from divmorph.pipeline.files import read_progress

    R = importlib.import_module("divmorph.pipeline.report")
    out, profiles = copied_run(finished_run, tmp_path)
    arm = out / "transfer" / "Escape" / "scratch" / "seed-0"
    before = (read_progress(out / "student"), read_eval(arm / "eval.csv"), R.read_returns(out / "evaluate" / "returns.csv"))
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(["report", *base]) == 0
    summary = (out / "summary.md").read_text()
    argv = sys.argv
    try:
        sys.argv = ["pack_logs.py", "--write", str(out)]
        runpy.run_path(str(Path(__file__).resolve().parents[1] / "tools" / "pack_logs.py"), run_name="__main__")
    finally:
        sys.argv = argv
    assert not list(out.rglob("progress.csv")) and not list(out.rglob("eval.csv")) and (out / "evaluate" / "returns.csv.gz").is_file()
    after = (read_progress(out / "student"), read_eval(arm / "eval.csv"), R.read_returns(out / "evaluate" / "returns.csv"))
    assert before[0].keys() == after[0].keys() and all(np.array_equal(before[0][k], after[0][k], equal_nan=True) for k in before[0])
    assert before[1:] == after[1:]
    assert cli(["report", *base]) == 0
    # the time stamps ("written 2026-11-26 11:33", "Written ...") move on a minute boundary between the two reports
    strip = lambda text: [line for line in text.splitlines() if "finished in" not in line and "written 20" not in line.lower()]  # noqa: E731
    assert strip((out / "summary.md").read_text()) == strip(summary)
    assert cli(["evaluate", *base]) == 0  # nothing to do: the packed evaluation counts
    assert (out / "evaluate" / "returns.csv.gz").is_file() and not (out / "evaluate" / "returns.csv").exists()


def test_packed_transfer_runs_keep_every_evaluation_and_update(finished_run, tmp_path):
    """tools/pack_transfer_runs.py keeps, for each finished transfer run, every evaluated episode (returns
    to 0.01) and one training row per PPO update, skips a run without done.json, and packs byte-identically
    twice (a re-pack of the same runs changes nothing in git)."""
    import pandas as pd

    from divmorph.pipeline.curves import read_eval

    spec = importlib.util.spec_from_file_location(
        "pack_transfer_runs", Path(__file__).resolve().parents[1] / "tools" / "pack_transfer_runs.py"
    )
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    out, _ = copied_run(finished_run, tmp_path)
    finished = sorted(p.parent for p in out.glob("transfer/*/*/seed-*/done.json"))
    assert len(finished) >= 2
    (finished[-1] / "done.json").unlink()  # as if it were still running
    results = tmp_path / "results"
    assert tool.pack(results, out, "v") == [f"{p.parent.parent.name}/{p.parent.name}/{p.name}" for p in finished[:-1]]
    run = finished[0]
    task, arm = run.parent.parent.name, run.parent.name
    packed = pd.read_csv(results / "v" / "transfer" / task / arm / run.name / "eval.csv.gz")
    original = pd.DataFrame(read_eval(run / "eval.csv"))
    assert len(packed) == len(original) > 0
    assert np.allclose(packed["return"], original["return"].astype(float), atol=0.005)
    assert not (results / "v" / "transfer" / finished[-1].parent.parent.name / finished[-1].parent.name / finished[-1].name).exists()
    training = pd.read_csv(results / "training-v.csv.gz")
    mine = training[(training.task == task) & (training.arm == arm) & (training.seed == int(run.name.removeprefix("seed-")))]
    progress = pd.concat([pd.read_csv(p) for p in sorted(run.glob("logs/run-*/progress.csv*"))])
    assert len(mine) == progress["train/clip_fraction"].notna().sum() > 0
    assert mine["clip_fraction"].notna().all() and mine["timesteps"].is_monotonic_increasing
    first = {p: p.read_bytes() for p in results.rglob("*") if p.is_file()}
    tool.pack(results, out, "v")
    assert {p: p.read_bytes() for p in results.rglob("*") if p.is_file()} == first


def read_returns(path: Path) -> dict[tuple[str, ...], float]:
    with open(path, newline="") as f:
        return {(r["model"], r["task"], r["split"], r["morphology"], r["episode"]): float(r["return"]) for r in csv.DictReader(f)}


def test_student_overrides_size_one_student_and_name_only_known_students(finished_run, tmp_path):
    """``student.overrides: {deploy-g1k1: {d_model: 24, ff_dim: 48}}`` widens that student alone; an
    override for a student that does not exist stops the distill stage before any training."""
    from divmorph.pipeline.distill import distill, distill_run

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles, overrides={"student.overrides": {"deploy-g1k1": {"d_model": 24, "ff_dim": 48}}})
    widths = {
        name: distill_run(profile, out, name, progress_bar=False).make_model().policy.config["d_model"]
        for name in ("deploy-g1k1", "divmorph")
    }
    assert widths == {"deploy-g1k1": 24, "divmorph": 16}
    wrong = load_profile("tiny", profiles, overrides={"student.overrides": {"deploy-g9k9": {"d_model": 24}}})
    with pytest.raises(ConfigError, match="deploy-g9k9"):
        distill(wrong, out, progress_bar=False, students=["divmorph"])


def test_a_deployment_student_is_distilled_exported_and_reported_beside_the_student(finished_run, tmp_path):
    import shutil

    source, profiles = finished_run
    out = tmp_path / "copy"
    shutil.copytree(source, out)
    evaluated = (out / "evaluate" / "returns.csv").read_text()
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(["distill", *base, "--students", "deploy-g1k1"]) == 0
    assert DivMorphPolicy is type(__import__("stable_baselines3").PPO.load(out / "students" / "deploy-g1k1" / "model.zip").policy)
    assert cli(["export", *base, "--task", "FT", "--student", "deploy-g1k1"]) == 0
    deployed = [json.loads(p.read_text()) for p in sorted((out / "export" / "deploy-g1k1").glob("*/report.json"))]
    default = {r["robot"]: r for r in (json.loads(p.read_text()) for p in (out / "export").glob("*-FT/report.json"))}
    assert len(deployed) == 2 and all(r["student"] == "deploy-g1k1" and r["max_abs_diff"] <= 1e-5 for r in deployed)
    for r in deployed:  # the sparser diversion deploys a smaller actor than the default student's
        assert r["compact_weights"] < default[r["robot"]]["compact_weights"]
    assert cli(["distill", *base, "--students", "deploy-g1k1", "--arms", "scratch"]) == 2
    assert cli(["export", *base, "--student", "distilled"]) == 2  # a dense student has nothing to prune
    assert cli(["evaluate", *base]) == 0 and cli(["report", *base]) == 0
    # The finished evaluation grew by the new student's rows and kept every row it had.
    grown = (out / "evaluate" / "returns.csv").read_text().splitlines()
    assert grown[: len(evaluated.splitlines())] == evaluated.splitlines()
    assert {line.split(",")[0] for line in grown[len(evaluated.splitlines()) :]} == {"student-deploy-g1k1"}
    summary = (out / "summary.md").read_text()
    assert "| deploy-g1k1 | " in summary and "deploy-g1k1" in summary.split("## Findings")[1]
    with open(out / "export" / "summary.csv") as f:
        assert {row["student"] for row in csv.DictReader(f)} == {"divmorph", "deploy-g1k1"}


def test_every_arm_writes_a_curve_and_metrics(finished_run):
    out, _ = finished_run
    for arm in ARMS:
        with open(out / "transfer" / "Escape" / arm / "seed-0" / "eval.csv") as f:
            rows = list(csv.DictReader(f))
        # step 0 (zero-shot), every 64 steps, the end; 2 training + 2 novel robots, 1 episode each
        assert sorted({int(r["timesteps"]) for r in rows}) == [0, 64, 128], arm
        assert len(rows) == 3 * 4 and {r["split"] for r in rows} == {"train", "novel"}
        assert all(int(r["length"]) == 40 or float(r["return"]) == float(r["return"]) for r in rows)
    with open(out / "transfer" / "Escape" / "metrics.csv") as f:
        metrics = list(csv.DictReader(f))
    assert {(m["arm"], m["split"]) for m in metrics} == {(arm, split) for arm in ARMS for split in ("train", "novel")}
    for m in metrics:
        for k in ("zero_shot", "final", "auc"):  # means over seeds and robots inside their 95% bootstrap interval
            assert float(m[f"{k}_lo"]) <= float(m[k]) <= float(m[f"{k}_hi"]) and np.isfinite(float(m[k]))
        assert m["robots"] == "2"
        assert m["sample_efficiency"] in ("-", "from the start (zero-shot)") or m["sample_efficiency"].endswith(("x", "held it)"))
    # the zero-shot metric is the step-0 evaluation, averaged over robots
    with open(out / "transfer" / "Escape" / "divmorph" / "seed-0" / "eval.csv") as f:
        step0 = [float(r["return"]) for r in csv.DictReader(f) if r["timesteps"] == "0" and r["split"] == "novel"]
    divmorph_novel = next(m for m in metrics if m["arm"] == "divmorph" and m["split"] == "novel")
    assert np.isclose(float(divmorph_novel["zero_shot"]), np.mean(step0))


def test_the_papers_figures_come_with_their_numbers(finished_run):
    out, profiles = finished_run
    figures = out / "report" / "figures"
    for name in ("transfer-train", "transfer-novel", "deployment", "pareto", "ablation", "gates"):
        assert (figures / f"{name}.png").stat().st_size > (5_000 if name == "pareto" else 10_000), name  # a drawn figure
        with open(figures / f"{name}.csv") as f:
            assert list(csv.DictReader(f)), name
    with open(figures / "transfer-train.csv") as f:
        plotted = {r["arm"] for r in csv.DictReader(f)}
    assert plotted == {"divmorph", "scratch", "closest", "distilled", "modumorph", "grl"}
    with open(figures / "ablation.csv") as f:
        plotted = {r["arm"] for r in csv.DictReader(f)}
    assert plotted == {"divmorph", "no-kdiv-transformer", "no-kdiv-decoder", "no-orthogonality"}
    with open(figures / "deployment.csv") as f:
        bars = list(csv.DictReader(f))
    assert {r["model"] for r in bars} == {"teacher", "hyperdistill", "student"}
    sizes = {r["model"]: float(r["value"]) for r in bars if r["panel"].startswith("parameters") and r["task"] == "FT"}
    assert sizes["student"] < sizes["teacher"]  # the compact actor, pruned
    # the Pareto figure plots the same sizes against the training robots' returns, with intervals
    with open(figures / "pareto.csv") as f:
        points = {r["model"]: r for r in csv.DictReader(f) if r["task"] == "FT"}
    assert set(points) == {"teacher", "hyperdistill", "student"}
    assert all(np.isclose(float(points[m]["parameters"]), sizes[m]) for m in ("teacher", "student"))
    assert all(float(p["lo"]) <= float(p["return"]) <= float(p["hi"]) for p in points.values())
    smallest = min(points.values(), key=lambda p: float(p["parameters"]))
    assert smallest["pareto"] == "True"  # nothing is smaller, so nothing beats it
    (figures / "ablation.png").unlink()
    assert cli(["figure", "ablation", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out)]) == 0
    assert (figures / "ablation.png").is_file()


def test_the_pareto_front_keeps_what_no_smaller_actor_beats():
    from divmorph.pipeline.figures import pareto_front

    # (size, return): (5, 2) beats (5, 1) and (10, 1); (20, 3) buys more return for more size
    assert pareto_front([10, 5, 20, 5], [1, 2, 3, 1]) == [1, 2]
    assert pareto_front([1, 2, 3], [3, 2, 1]) == [0]


def test_closest_starts_from_the_teacher_the_embeddings_say(finished_run):
    from unimal_envs.instructions import shipped_embeddings

    out, _ = finished_run
    choice = json.loads((out / "transfer" / "Escape" / "closest-by-embedding.json").read_text())
    embeddings = shipped_embeddings()
    cosine = {
        t: float(embeddings["Escape"] @ embeddings[t] / np.linalg.norm(embeddings["Escape"]) / np.linalg.norm(embeddings[t]))
        for t in ("FT", "Patrol")
    }
    assert choice["closest"] == max(cosine, key=cosine.get)
    assert choice["scores"] == pytest.approx(cosine, abs=1e-5)
    source = json.loads((out / "transfer" / "Escape" / "closest" / "seed-0" / "source.json").read_text())
    assert source["source"] == f"teachers/{choice['closest']}"


def test_the_dense_distilled_student_is_metamorph_and_its_imitation_error_falls(finished_run):
    from stable_baselines3 import PPO

    out, _ = finished_run
    student = PPO.load(out / "students" / "distilled" / "model.zip", device="cpu")
    assert type(student.policy) is MetaMorphPolicy
    assert "task_embedding" in student.policy.features_extractor.exteroception  # how it tells the tasks apart
    with open(next((out / "students" / "distilled" / "logs").glob("run-*/progress.csv"))) as f:
        losses = [float(r["distill/loss"]) for r in csv.DictReader(f)]
    assert len(losses) >= 2 and losses[-1] < losses[0]
    # transfer fine-tunes it whole, from its distilled weights
    source = json.loads((out / "transfer" / "Escape" / "distilled" / "seed-0" / "source.json").read_text())
    assert source["source"] == "students/distilled"


def test_ablation_students_lack_what_they_claim(finished_run):
    from stable_baselines3 import PPO

    from sb3_divmorph.nn.layers import FactorizedLinear

    out, _ = finished_run

    def layers(folder):
        policy = PPO.load(folder / "model.zip", device="cpu").policy
        assert isinstance(policy, DivMorphPolicy) and policy.is_gated
        return {
            name: layer
            for name, layer in policy.named_modules()
            if isinstance(layer, FactorizedLinear) and name.startswith(("features_extractor.encoder", "mlp_extractor.policy_net"))
        }

    full = layers(out / "student")
    assert all(layer.n_tailors > 0 and layer.orthogonality_error() < 1e-5 for layer in full.values())
    for name, layer in layers(out / "students" / "no-kdiv-decoder").items():
        assert (layer.n_tailors == 0) == name.startswith("mlp_extractor"), name
    for name, layer in layers(out / "students" / "no-kdiv-transformer").items():
        assert (layer.n_tailors == 0) == name.startswith("features_extractor"), name
    free = layers(out / "students" / "no-orthogonality")
    for layer in free.values():
        assert not layer.orthogonal and isinstance(layer.square, th.nn.Parameter) and not hasattr(layer, "square_skew")
        assert layer.orthogonality_error() > 1e-3  # distillation moved the free square factor off the orthogonal group
    # the ablations are transferred the DivMorph way: fixed gates, learngene/tailor update ratio logged
    with open(next((out / "transfer" / "Escape" / "no-kdiv-decoder" / "seed-0" / "logs").glob("run-*/progress.csv"))) as f:
        assert "transfer/update_ratio" in next(csv.reader(f))


def test_grl_inherits_exactly_its_learngene_layers(finished_run):
    from stable_baselines3 import PPO

    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.grl import agent_folder, agent_run, read_learngene, read_plan, unit_tensors
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)

    def same(a, b, unit):
        return all(th.equal(x, y) for x, y in zip(unit_tensors(a, unit), unit_tensors(b, unit), strict=True))

    child_plan = read_plan(out, 1)[0]
    parent = PPO.load(agent_folder(out, 0, child_plan.parent) / "model.zip", device="cpu").policy
    child = agent_run(profile, out, 1, child_plan.index, progress_bar=False).make_model().policy  # the child at its start
    units = ["embedding", "block.0", "exteroception", "decoder"]
    for unit in units:
        assert same(child, parent, unit) == (unit in child_plan.learngene), unit
    learngene = read_learngene(out)
    best = PPO.load(out / learngene["folder"] / "model.zip", device="cpu").policy
    arm = transfer_run(profile, out, "Escape", "grl", 0, progress_bar=False).make_model().policy  # the grl arm at step 0
    for unit in units:
        assert same(arm, best, unit) == (unit in learngene["units"]), unit


def test_finetune_settings_reach_the_arms_that_start_from_trained_weights_only(finished_run):
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = finished_run
    profile = load_profile("tiny", profiles, overrides={"transfer.finetune_overrides": {"learning_rate": 1.25e-5}})
    rates = {
        arm: transfer_run(profile, out, "Escape", arm, 0, progress_bar=False).make_model().lr_schedule(1.0)
        for arm in ("scratch", "modumorph", "divmorph", "closest", "distilled", "grl")
    }
    assert rates["divmorph"] == rates["closest"] == rates["distilled"] == rates["grl"] == pytest.approx(1.25e-5)
    assert rates["scratch"] == rates["modumorph"] != pytest.approx(1.25e-5)
    from sb3_divmorph.algos.finetune import CriticWarmup

    profile = load_profile("tiny", profiles, overrides={"transfer.critic_warmup": 64})
    warmups = {
        arm: [c.steps for c in transfer_run(profile, out, "Escape", arm, 0, progress_bar=False).callbacks if isinstance(c, CriticWarmup)]
        for arm in ("scratch", "divmorph", "closest")
    }
    assert warmups == {"scratch": [], "divmorph": [64], "closest": [64]}
    with pytest.raises(ConfigError, match="critic_warmup"):
        load_profile("tiny", profiles, overrides={"transfer.critic_warmup": -1})
    with pytest.raises(ConfigError, match=r"transfer.finetune_overrides: unknown key\(s\) \['lerning_rate'\]"):
        load_profile("tiny", profiles, overrides={"transfer.finetune_overrides": {"lerning_rate": 1e-4}})
    # transfer.desired_kl: every arm's rate adapts to a KL per update (one step-size rule for every parameterisation)
    from sb3_divmorph.algos.adaptive_rate import AdaptiveLearningRate

    profile = load_profile("tiny", profiles, overrides={"transfer.desired_kl": 0.01})
    adapting = {
        arm: [
            c.desired_kl
            for c in transfer_run(profile, out, "Escape", arm, 0, progress_bar=False).callbacks
            if isinstance(c, AdaptiveLearningRate)
        ]
        for arm in ("scratch", "divmorph", "distilled")
    }
    assert adapting == {"scratch": [0.01], "divmorph": [0.01], "distilled": [0.01]}
    with pytest.raises(ConfigError, match="desired_kl"):
        load_profile("tiny", profiles, overrides={"transfer.desired_kl": 0})


def test_a_finished_pipeline_is_skipped_not_recomputed(finished_run, capsys):
    out, profiles = finished_run
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("**/model.zip")}
    assert cli(["pipeline", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]) == 0
    # nothing was trained again: every model is the file it was, and each stage says it skipped
    assert {p: p.stat().st_mtime_ns for p in out.glob("**/model.zip")} == stamps
    printed = capsys.readouterr().out
    assert "skipped" in printed and "steps ->" not in printed


def test_a_killed_run_resumes_from_its_last_checkpoint(tmp_path):
    profiles = write_profiles(tmp_path, teachers__n_timesteps=4096, teachers__checkpoint_every=256, teachers__tasks=["FT"])
    out = tmp_path / "run"
    command = [
        sys.executable,
        "-m",
        "divmorph.cli",
        "teachers",
        "--profile",
        "tiny",
        "--profiles",
        str(profiles),
        "--out",
        str(out),
        "--no-progress",
    ]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoints = out / "teachers" / "FT" / "checkpoints"
    deadline = time.time() + 240
    while time.time() < deadline and (latest_checkpoint(checkpoints) is None or _steps(checkpoints) < 512):
        time.sleep(0.2)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    saved = _steps(checkpoints)
    assert saved >= 512, "no checkpoint was written before the kill"
    assert not (out / "teachers" / "FT" / "done.json").exists()

    assert cli(["teachers", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]) == 0
    assert read_done(out / "teachers" / "FT")["num_timesteps"] == 4096
    logs = sorted((out / "teachers" / "FT" / "logs").glob("run-*/progress.csv"))
    assert len(logs) == 2
    with open(logs[1]) as f:
        resumed = [int(float(row["time/total_timesteps"])) for row in csv.DictReader(f)]
    # the second attempt started from the checkpoint (lost at most one interval), not from zero
    assert resumed[0] > saved
    assert resumed[0] <= saved + 256
    assert not [p for p in out.glob("**/*") if ".tmp" in p.name or ".staging" in p.name]


def test_a_stopped_command_keeps_the_steps_since_the_last_checkpoint_and_says_how_to_go_on(tmp_path):
    """SIGTERM (`kill`, a scheduler's preemption) between checkpoints stops a command as Ctrl-C does:
    it saves the teacher where it stopped and exits 143 with a sentence instead of a traceback.
    (SIGTERM, because a test runner's workers may ignore SIGINT, and their children inherit that;
    Ctrl-C's KeyboardInterrupt takes the same path, ``test_usability``'s interrupted-run test.)"""
    profiles = write_profiles(tmp_path, teachers__n_timesteps=100_000, teachers__checkpoint_every=1_000_000, teachers__tasks=["FT"])
    out = tmp_path / "run"
    command = [
        sys.executable,
        "-m",
        "divmorph.cli",
        "teachers",
        "--profile",
        "tiny",
        "--profiles",
        str(profiles),
        "--out",
        str(out),
        "--no-progress",
    ]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out / "teachers" / "FT" / "logs" / "run-0" / "progress.csv"
    deadline = time.time() + 240
    while time.time() < deadline and (not log.is_file() or len(log.read_text().splitlines()) < 4):
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    assert "[interrupted]" in stdout
    saved = _steps(out / "teachers" / "FT" / "checkpoints")
    assert saved >= 2 * 64  # three rollouts were logged before the signal (64 steps each); the last may have been in its update
    assert not (out / "teachers" / "FT" / "done.json").exists()


def test_a_finished_stage_continues_past_its_budget_from_its_final_model(tmp_path, capsys):
    """``--continue teachers`` with a larger budget carries a finished teacher on from its final model
    (its weights, statistics and step count), as SB3's ``reset_num_timesteps=False``: the new attempt
    starts where the old one ended; without the flag the change is refused, naming it; a smaller
    budget, another changed setting or a stage that cannot continue are refused too."""
    profiles = write_profiles(tmp_path, teachers__n_timesteps=128, teachers__tasks=["FT"])
    out = tmp_path / "run"
    base = ["teachers", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(base) == 0
    teacher = out / "teachers" / "FT"
    first = PPO.load(teacher / "model.zip", device="cpu")
    assert read_done(teacher)["num_timesteps"] == 128
    assert cli([*base, "--set", "teachers.n_timesteps=256"]) == 2
    assert "teachers.n_timesteps: 128 -> 256" in capsys.readouterr().err
    assert cli([*base, "--set", "teachers.n_timesteps=256", "--set", "seed=4", "--continue", "teachers"]) == 2
    assert cli([*base, "--set", "teachers.n_timesteps=64", "--continue", "teachers"]) == 2
    assert "needs a larger teachers.n_timesteps" in capsys.readouterr().err
    assert cli([*base, "--set", "distill.n_timesteps=256", "--continue", "distill"]) == 2
    assert "--continue takes" in capsys.readouterr().err
    assert read_done(teacher)["num_timesteps"] == 128, "a refused command changes nothing"

    assert cli([*base, "--set", "teachers.n_timesteps=256", "--continue", "teachers"]) == 0
    assert read_done(teacher)["num_timesteps"] == 256 and not (teacher / "checkpoints").exists()
    logs = sorted((teacher / "logs").glob("run-*/progress.csv"))
    with open(logs[-1]) as f:
        continued = [int(float(row["time/total_timesteps"])) for row in csv.DictReader(f)]
    assert len(logs) == 2 and 128 < continued[0] <= 192 and continued[-1] == 256
    resumed = PPO.load(teacher / "model.zip", device="cpu")
    before, after = first.policy.state_dict(), resumed.policy.state_dict()
    assert resumed.num_timesteps == 256 and any(not th.equal(before[k], after[k]) for k in before), "the continued model trained on"
    assert json.loads((out / "run.json").read_text())["history"][-1]["continued"] == ["teachers"]
    assert cli(base + ["--set", "teachers.n_timesteps=256"]) == 0, "the continued run is the run's record now"


def _steps(checkpoints: Path) -> int:
    pointer = checkpoints / "latest.json"
    try:
        return json.loads(pointer.read_text())["num_timesteps"]
    except (FileNotFoundError, json.JSONDecodeError):
        return 0


def test_profile_errors_name_the_key_and_the_choices(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['n_timestep'\].*valid keys"):
        load_profile("tiny", write_profiles(tmp_path, distill__n_timestep=5))
    with pytest.raises(ConfigError, match="unknown profile 'nope'.*tiny"):
        load_profile("nope", write_profiles(tmp_path))
    with pytest.raises(ConfigError, match="Escape"):
        load_profile("tiny", write_profiles(tmp_path, teachers__tasks=["FT", "Escape"]))
    with pytest.raises(ConfigError, match="not in transfer.tasks"):
        load_profile("tiny", write_profiles(tmp_path, transfer__instructions={"PointNav": "go"}))
    with pytest.raises(ConfigError, match="ppo_loss needs beta"):
        load_profile("tiny", write_profiles(tmp_path, distill__ppo_loss=True))
    with pytest.raises(ConfigError, match=r"teachers.n_timesteps must be a positive whole number of env steps, got -5"):
        load_profile("tiny", write_profiles(tmp_path, teachers__n_timesteps=-5))
    assert load_profile("tiny", write_profiles(tmp_path, teachers__n_timesteps=2e3)).teachers.n_timesteps == 2000
    zoo = tmp_path / "zoo.yml"
    zoo.write_text("Unimal-FT-v0:\n  n_timesteps: 10\n  learning_rat: 0.1\n")
    with pytest.raises(ConfigError, match="learning_rat"):
        load_zoo_entry(zoo, "Unimal-FT-v0")
    with pytest.raises(ConfigError, match="no entry for Unimal-VT-v0"):
        load_zoo_entry(zoo, "Unimal-VT-v0")
    assert load_profile("demo").name == "demo" and load_profile("gpu").transfer.tasks


@pytest.mark.parametrize("name", sorted(load_profiles()))
def test_every_shipped_profile_builds_its_models(name):
    """A shipped profile whose student cannot divert a layer (or whose teacher cannot be built)
    fails here, not hours into a run."""
    profile = load_profile(name)
    env = gym.make("Unimal-MultiTask-v1", tasks=list(profile.teachers.tasks), morphologies=morphology_files("train")[:1])
    policy = DivMorphPolicy(env.observation_space, env.action_space, lambda _: 1e-3, **profile.student.policy_kwargs)
    assert policy.is_gated
    teacher_kwargs = {**load_zoo_entry(profile.teachers.hyperparams, "Unimal-VT-v0").policy_kwargs, **profile.teachers.policy_kwargs}
    MetaMorphPolicy(env.observation_space, env.action_space, lambda _: 1e-3, **teacher_kwargs)


def test_missing_stages_and_bad_arguments_give_clear_errors(tmp_path, capsys):
    profiles = write_profiles(tmp_path)
    out = tmp_path / "empty"
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(["distill", *base]) == 2
    assert "teacher for FT not found" in capsys.readouterr().err
    assert cli(["transfer", *base, "--task", "Escape"]) == 2
    assert "no distilled student" in capsys.readouterr().err
    assert cli(["transfer", *base, "--task", "FT"]) == 2
    assert "not one of" in capsys.readouterr().err
    # commands that read a run name a missing folder as such (not "run the stages first")
    assert cli(["export", *base, "--morphology", "nobody"]) == 2
    assert f"no such run folder: {out}" in capsys.readouterr().err
    assert cli(["teachers", *base, "--task", "Walk"]) == 2
    assert "unknown task(s) 'Walk'" in capsys.readouterr().err
    assert cli(["teachers", *base, "--task", "Escape"]) == 2
    assert "no teacher" in capsys.readouterr().err
    assert cli(["report", "--profile", "missing", "--profiles", str(profiles)]) == 2
    assert "unknown profile" in capsys.readouterr().err
    assert cli(["report", *base]) == 2
    assert f"no such run folder: {out}" in capsys.readouterr().err
    # none of these failures left a run folder behind
    assert not out.exists()
    # in a run folder that exists: a bad robot is named, and a report of a run where nothing has
    # finished (it would describe models that do not exist) is refused
    out.mkdir()
    assert cli(["export", *base, "--morphology", "nobody"]) == 2
    assert "unknown morphology 'nobody'" in capsys.readouterr().err
    assert cli(["report", *base]) == 2
    assert "nothing to report" in capsys.readouterr().err


def test_command_line_overrides_reach_the_profile_and_are_validated(tmp_path, capsys):
    import argparse

    from divmorph.cli.run_folder import profile_overrides as _overrides

    profiles = write_profiles(tmp_path)
    args = argparse.Namespace(
        seed=7,
        device="cpu",
        train_robots="3",
        novel_robots="train",
        set=["teachers.n_timesteps=4096", "transfer.tasks=[PointNav]", "max_episode_steps=50"],
    )
    profile = load_profile("tiny", profiles, _overrides(args))
    assert (profile.seed, profile.device, profile.train_robots, profile.max_episode_steps) == (7, "cpu", 3, 50)
    assert (profile.novel_set, profile.novel_robots) == ("train", None)
    assert profile.teachers.n_timesteps == 4096 and profile.transfer.tasks == ["PointNav"]
    # typos and bad values are refused like the YAML's, before anything runs
    out = tmp_path / "run"
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(["teachers", *base, "--set", "teachers.n_timestep=5"]) == 2
    assert "unknown key(s) ['n_timestep']" in capsys.readouterr().err
    assert cli(["teachers", *base, "--set", "transfer.tasks=[FT]"]) == 2
    assert "transfer.tasks" in capsys.readouterr().err
    assert cli(["teachers", *base, "--set", "nonsense"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err
    assert not out.exists()


def test_a_run_is_only_continued_with_the_settings_it_was_started_with(finished_run, tmp_path, capsys):
    import shutil

    source, profiles = finished_run
    out = tmp_path / "copy"
    shutil.copytree(source, out)
    record = json.loads((out / "run.json").read_text())
    assert record["device_used"] == "cpu" and record["configuration"]["seed"] == 0
    assert record["versions"]["torch"] and record["robots"]["train"]["robots"] and record["history"]
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    # the reported scenario: other seed, robots and episode length on a finished run
    assert cli(["pipeline", *base, "--seed", "3", "--train-robots", "1", "--set", "max_episode_steps=20"]) == 2
    err = capsys.readouterr().err
    assert "seed: 0 -> 3" in err and "train_robots: 2 -> 1" in err and "max_episode_steps" in err
    assert "teachers: " in err and "--redo teachers" in err and "--force" in err
    summary = (out / "summary.md").read_text()
    assert cli(["report", *base, "--seed", "3"]) == 2 and (out / "summary.md").read_text() == summary
    assert cli(["report", *base, "--redo", "nonsense"]) == 2 and "unknown stage" in capsys.readouterr().err
    # a change that only the export depends on: --redo export retrains it, keeping the old one aside
    old_export = sorted(p.relative_to(out / "export") for p in (out / "export").glob("*/report.json"))
    assert cli(["export", *base, "--set", "export.latency_repeats=3"]) == 2
    assert "export: export.latency_repeats: 5 -> 3" in capsys.readouterr().err
    assert cli(["export", *base, "--set", "export.latency_repeats=3", "--redo", "export"]) == 0
    superseded = next((out / "superseded").iterdir())
    assert sorted(p.relative_to(superseded / "export") for p in (superseded / "export").glob("*/report.json")) == old_export
    assert sorted(p.relative_to(out / "export") for p in (out / "export").glob("*/report.json")) == old_export
    assert (out / "teachers" / "FT" / "done.json").is_file() and (out / "evaluate" / "done.json").is_file()
    history = json.loads((out / "run.json").read_text())["history"][-1]
    assert history["retrained"] == ["export"] and history["changed"] == ["export.latency_repeats: 5 -> 3"]
    # a change that no begun stage depends on is recorded without ceremony
    shutil.rmtree(out / "evaluate")
    assert cli(["report", *base, "--set", "export.latency_repeats=3", "--set", "evaluate.episodes=2"]) == 0
    assert json.loads((out / "run.json").read_text())["history"][-1]["changed"] == ["evaluate.episodes: 1 -> 2"]
    # --redo of an upstream stage retrains what was built on it too (here: the export)
    assert cli(["report", *base, "--set", "export.latency_repeats=3", "--set", "evaluate.episodes=2", "--redo", "transfer"]) == 0
    assert not (out / "transfer").exists() and not (out / "export").exists() and (out / "student" / "done.json").is_file()
    # cuda where there is none is refused, not silently cpu
    if not th.cuda.is_available():
        assert cli(["report", *base, "--set", "export.latency_repeats=3", "--set", "evaluate.episodes=2", "--device", "cuda"]) == 2
        assert "no CUDA device" in capsys.readouterr().err


def test_a_lost_normaliser_is_an_error_not_a_silent_fallback(finished_run, tmp_path, capsys):
    import shutil

    source, profiles = finished_run
    out = tmp_path / "copy"
    shutil.copytree(source, out)
    for stage in ("export", "evaluate"):
        shutil.rmtree(out / stage)
    (out / "student" / "vecnormalize.pkl").unlink()
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    assert cli(["export", *base, "--task", "FT"]) == 2
    assert "vecnormalize.pkl is missing" in capsys.readouterr().err
    assert not list((out / "export").glob("*/actor.*")) if (out / "export").exists() else True
    assert cli(["evaluate", *base]) == 2
    assert "vecnormalize.pkl is missing" in capsys.readouterr().err
    # the copy keeps everything else: a failed command never deletes results
    assert (out / "student" / "model.zip").is_file() and (out / "teachers").is_dir()


def test_a_checkpoint_for_another_observation_space_is_refused(finished_run, tmp_path):
    from gymnasium import spaces
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    from sb3_divmorph.algos.distillation import SpaceMismatchError
    from divmorph.pipeline.training import TrainingRun

    out, _ = finished_run

    class Narrow(gym.ObservationWrapper):
        def __init__(self, env):
            super().__init__(env)
            self.observation_space = spaces.Dict({**env.observation_space.spaces, "goal": spaces.Box(-1, 1, (2,), np.float32)})

        def observation(self, obs):
            return {**obs, "goal": obs["goal"][:2]}

    def make_env():
        return VecMonitor(DummyVecEnv([lambda: Narrow(gym.make("Unimal-FT-v0", morphologies=morphology_files("train")[:1]))]))

    run = TrainingRun(out / "teachers" / "FT", 10, 10, make_model=None, make_env=make_env)
    with pytest.raises(SpaceMismatchError, match="goal"):
        run.load_final()


def test_a_transfer_instruction_reaches_the_gates_input():
    from divmorph.pipeline.transfer import robot_observations

    robots = morphology_files("train")[:1]
    default = robot_observations("Unimal-Escape-v0", robots)
    custom = robot_observations("Unimal-Escape-v0", robots, instruction="Climb out of the crater as fast as you can.")
    assert not np.allclose(default["task_embedding"], custom["task_embedding"])
    assert np.isclose(np.linalg.norm(custom["task_embedding"]), 1.0, atol=1e-4)


def test_closest_by_return_picks_the_best_zero_shot_teacher(finished_run):
    from divmorph.pipeline.evaluate import evaluate_model
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import closest_task

    out, profiles = finished_run
    profile = load_profile("tiny", profiles)
    choice = closest_task(profile, out, "Escape", by="return")
    robots = profile_robots(profile, "train")
    returns = {
        t: np.mean([r["return"] for r in evaluate_model(out / "teachers" / t, "Escape", robots, 1, 40, profile.seed)])
        for t in ("FT", "Patrol")
    }
    assert choice["scores"] == pytest.approx(returns)
    assert choice["closest"] == max(returns, key=returns.get)

    # a run folder begun from another teacher is refused, never silently replaced or mixed
    other = out / "transfer" / "Escape" / "closest" / "seed-7"
    other.mkdir()
    (other / "source.json").write_text(json.dumps({"arm": "closest", "seed": 7, "source": "teachers/Elsewhere"}))
    try:
        assert (
            cli(
                [
                    "transfer",
                    "--profile",
                    "tiny",
                    "--profiles",
                    str(profiles),
                    "--out",
                    str(out),
                    "--arms",
                    "closest",
                    "--seeds",
                    "7",
                    "--no-progress",
                ]
            )
            == 2
        )
        assert list(other.iterdir()) == [other / "source.json"]
    finally:
        (other / "source.json").unlink()
        other.rmdir()


def test_report_gives_robot_intervals_and_answers_the_zero_shot_claim():
    """Each robot counts once (its episodes averaged) in the returns table's interval; the zero-shot
    comparison puts a student that keeps its return on novel robots above a HyperDistill student that
    keeps half of it, and not the other way round."""
    import importlib

    R = importlib.import_module("divmorph.pipeline.report")
    profile = load_profile("demo")
    rng = np.random.default_rng(0)
    rows = []
    for model, kept in (("student", 1.0), ("hyperdistill", 0.5)):
        for split, scale in (("train", 1.0), ("novel", kept)):
            for robot in range(12):
                for episode in range(3):
                    value = scale * (100 + 10 * robot) + rng.normal(0, 1)
                    rows.append(
                        {"model": model, "task": "FT", "split": split, "morphology": f"r{robot}", "episode": episode, "return": value}
                    )
    table, groups = R.returns_table(rows)
    assert len(groups[("student", "FT", "train")]) == 12  # one value per robot
    assert "(12 x 3)" in table[2] and "[" in table[2]
    lines = R.zero_shot_comparison(profile, rows)
    ft = next(line for line in lines if line.startswith("| FT ("))
    difference = ft.split("|")[4]
    lo, hi = (float(x) for x in difference[difference.index("[") + 1 : difference.index("]")].split(","))
    assert 0.3 < lo <= 0.5 <= hi < 0.7, ft  # kept 1.0 vs 0.5
    swapped = [{**row, "model": {"student": "hyperdistill", "hyperdistill": "student"}[row["model"]]} for row in rows]
    ft = next(line for line in R.zero_shot_comparison(profile, swapped) if line.startswith("| FT ("))
    assert float(ft.split("|")[4].split("[")[0]) < 0


def test_out_of_distribution_robots_are_a_split_of_their_own_in_the_report():
    """With an ``ood_set`` the report gives the out-of-distribution robots their own column and their own
    zero-shot comparison, computed from their rows only (the novel robots' numbers do not change)."""
    import importlib

    R = importlib.import_module("divmorph.pipeline.report")
    profile = load_profile("demo", overrides={"ood_set": "novel"})
    rows = [
        {"model": model, "task": "FT", "split": split, "morphology": f"{split}{robot}", "episode": 0, "return": value + robot}
        for model, values in (("student", (100, 60, 5)), ("hyperdistill", (100, 30, 5)))
        for split, value in zip(("train", "novel", "ood"), values)
        for robot in range(6)
    ]
    table, _ = R.returns_table(rows)
    assert "out-of-distribution robots" in table[0] and table[2].count("|") == 6
    novel = next(line for line in R.zero_shot_comparison(profile, rows) if line.startswith("| FT ("))
    ood = next(line for line in R.zero_shot_comparison(profile, rows, split="ood") if line.startswith("| FT ("))
    assert novel.split("|")[5].strip().startswith("+30.0") and ood.split("|")[5].strip().startswith("+0.0")
    without = [row for row in rows if row["split"] != "ood"]
    assert R.zero_shot_comparison(profile, without, split="ood") == []
    assert "out-of-distribution" not in R.returns_table(without)[0][0]
    from divmorph.pipeline.robots import profile_robots, profile_splits

    assert profile_splits(profile) == ("train", "novel", "ood") and profile_splits(load_profile("demo")) == ("train", "novel")
    assert profile_robots(profile, "ood")[0].parent.name in ("novel", "xml")
    with pytest.raises(ValueError, match="no out-of-distribution robots"):
        profile_robots(load_profile("demo"), "ood")


def test_student_shares_pair_the_robots_and_judge_the_90_percent_bar_by_the_interval():
    """A student at 97% of its teacher on every robot passes; one at 50% fails; one at 100% on half the
    robots and 75% on the other half (86% of the teacher's mean) does not pass. Pairing matters: the
    robots differ ten-fold in return, so an unpaired interval would straddle the bar for the first."""
    import importlib

    R = importlib.import_module("divmorph.pipeline.report")
    profile = load_profile("demo")
    rows = []
    scales = {"teacher": [1.0] * 20, "student": [0.97] * 20, "student-distilled": [0.5] * 20, "hyperdistill": [1.0, 0.75] * 10}
    for model, per_robot in scales.items():
        for robot, scale in enumerate(per_robot):
            for episode in range(2):
                rows.append(
                    {
                        "model": model,
                        "task": "FT",
                        "split": "train",
                        "morphology": f"r{robot}",
                        "episode": episode,
                        "return": scale * 100 * (1 + robot % 10),
                    }
                )
    table = R.student_shares(profile, rows)
    header = [c.strip() for c in table[4].split("|")[1:-1]]
    ft = dict(zip(header, (c.strip() for c in next(line for line in table if line.startswith("| FT (")).split("|")[1:-1])))
    assert ft["student"].endswith("yes") and "97%" in ft["student"]
    assert ft["student-distilled"].endswith("no")
    assert ft["hyperdistill"].endswith(("no", "unclear")) and "86%" in ft["hyperdistill"]
    negative = [{**row, "return": row["return"] - 1000} for row in rows if row["model"] in ("teacher", "student")]
    ft = next(line for line in R.student_shares(profile, negative) if line.startswith("| FT ("))
    assert "n/a" in ft and "yes" not in ft  # no share of a teacher whose return is below 0


def test_report_figures_label_axes_and_give_each_task_its_own_scale(tmp_path, monkeypatch):
    import importlib

    R = importlib.import_module("divmorph.pipeline.report")  # the module (the package exports a function of that name)
    figures = []
    monkeypatch.setattr(R.plt, "close", figures.append)
    groups = {("teacher", "FT", "train"): [900.0, 20.0], ("student", "FT", "train"): [800.0], ("teacher", "Patrol", "novel"): [3.0]}
    R.plot_returns(groups, tmp_path / "returns.png", "a title naming the robots")
    gates = {
        "task_gates": np.eye(3),
        "tasks": np.array(["FT", "VT", "Patrol"]),
        "morphology_gates": np.eye(2),
        "robots": np.array(["a", "b"]),
    }
    R.plot_gates(gates, tmp_path / "gates.png")
    returns_fig, gates_fig = figures
    panels = [ax for ax in returns_fig.axes if ax.get_title()]
    assert [ax.get_title() for ax in panels] == ["FT", "Patrol"]  # one panel, one y scale per task
    assert all(ax.get_ylabel() for ax in panels) and returns_fig._suptitle.get_text() == "a title naming the robots"
    colour_bars = [ax for ax in gates_fig.axes if ax.get_ylabel().startswith("correlation")]
    assert len(colour_bars) == 2


def test_a_transfer_outside_the_profile_is_evaluated_reported_and_exported_from_the_right_model(finished_run, tmp_path):
    import shutil

    source, profiles = finished_run
    out = tmp_path / "copy"
    shutil.copytree(source, out)
    base = ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]
    # PointNav is not among the profile's transfer tasks; exported before its transfer: zero-shot
    assert cli(["export", *base, "--task", "PointNav"]) == 0
    reports = sorted((out / "export").glob("*-PointNav/report.json"))
    assert reports and all("zero-shot" in json.loads(p.read_text())["source_label"] for p in reports)
    assert cli(["transfer", *base, "--task", "PointNav", "--arms", "divmorph,scratch", "--seeds", "0", "4"]) == 0
    # after the transfer the same command exports the transferred student, not the stale zero-shot actor
    assert cli(["export", *base, "--task", "PointNav"]) == 0
    for path in reports:
        report = json.loads(path.read_text())
        assert report["source_label"] == "transferred student" and "transfer/PointNav/divmorph" in report["source"]
    shutil.rmtree(out / "evaluate")
    assert cli(["evaluate", *base]) == 0 and cli(["report", *base]) == 0
    with open(out / "evaluate" / "returns.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["task"] == "PointNav"]
    assert {r["model"] for r in rows} == {"student", "transfer-divmorph", "transfer-scratch"}
    assert sum(r["model"] == "transfer-scratch" for r in rows) == 2 * 4  # seeds 0 and 4, on 2 + 2 robots
    summary = (out / "summary.md").read_text()
    assert "transfer PointNav (scratch, seed 4)" in summary and "| PointNav | " in summary


def test_a_run_is_evaluated_and_reported_from_its_own_records(finished_run, tmp_path, monkeypatch):
    """``divmorph evaluate --run FOLDER`` needs no profile: the run's run.json says what it was."""
    import shutil

    source, _ = finished_run
    out = tmp_path / "copy"
    shutil.copytree(source, out)
    shutil.rmtree(out / "evaluate")
    monkeypatch.chdir(tmp_path)  # neither the profiles file of the run nor the source tree is needed
    assert cli(["evaluate", "--run", str(out), "--no-progress"]) == 0
    assert cli(["report", "--run", str(out), "--no-progress"]) == 0
    assert "# DivMorph pipeline — profile `tiny`" in (out / "summary.md").read_text()
    with open(out / "evaluate" / "returns.csv") as f:
        assert {r["model"] for r in csv.DictReader(f)} >= {"teacher", "student"}


def test_findings_put_the_hyperdistill_student_beside_the_others_when_it_was_evaluated():
    from divmorph.pipeline.report import findings

    profile = load_profile("demo")
    groups = {
        (model, task, split): [value]
        for task in profile.teachers.tasks
        for split in ("train", "novel")
        for model, value in (("teacher-untrained", 1.0), ("teacher", 100.0), ("student", 95.0), ("student-distilled", 80.0))
    }
    without = "\n".join(findings(profile, groups, []))
    assert "HyperDistill" not in without
    groups.update(
        {("hyperdistill", task, split): [value] for task in profile.teachers.tasks for split, value in (("train", 70.0), ("novel", 12.5))}
    )
    rows = findings(profile, groups, [])
    header = next(line for line in rows if line.startswith("| task"))
    assert "| HyperDistill student |" in header and header.endswith("teacher / student / HyperDistill |")
    first = next(line for line in rows if line.startswith(f"| {profile.teachers.tasks[0]} "))
    assert first.count("|") == header.count("|")
    assert "| 70.0 |" in first and first.endswith("| 100.0 / 95.0 / 12.5 |")


def test_a_branch_reuses_a_runs_stages_and_trains_only_what_follows(finished_run, tmp_path, capsys):
    """``divmorph branch``: a longer transfer in a new folder, on the source's teachers and students, untouched."""
    source, _ = finished_run
    stamps = {p: p.stat().st_mtime_ns for p in source.rglob("*") if p.is_file()}
    out = tmp_path / "longer"
    assert cli(["branch", "--from", str(source), "--out", str(out)]) == 0
    for linked in ("teachers/FT", "teachers/Patrol", "student", "students/distilled", "hyperdistill", "grl"):
        assert (out / linked).is_symlink() and (out / linked).resolve() == (source / linked).resolve(), linked
        assert not os.path.isabs(os.readlink(out / linked))  # relative: the pair of folders can move together
    assert not (out / "transfer").exists()

    # a change of what the linked stages were trained with is refused in the branch...
    assert cli(["teachers", "--run", str(out), "--set", "teachers.n_timesteps=256", "--no-progress"]) == 2
    assert "teachers: teachers.n_timesteps: 128 -> 256" in capsys.readouterr().err
    # ...a new transfer budget trains there, from the source's student, skipping the reused stages
    assert cli(["transfer", "--run", str(out), "--set", "transfer.n_timesteps=192", "--arms", "divmorph,closest", "--no-progress"]) == 0
    for arm in ("divmorph", "closest"):
        assert read_done(out / "transfer" / "Escape" / arm / "seed-0")["num_timesteps"] >= 192
        assert not (out / "transfer" / "Escape" / arm / "seed-0").is_symlink()
    history = json.loads((out / "run.json").read_text())["history"]
    assert history[-2]["branched_from"] == str(source) and history[-1]["changed"] == ["transfer.n_timesteps: 128 -> 192"]
    assert {p: p.stat().st_mtime_ns for p in source.rglob("*") if p.is_file()} == stamps  # nothing written in the source

    # bad input: no run folder to branch from, a folder that already holds files
    assert cli(["branch", "--from", str(tmp_path / "nothing"), "--out", str(tmp_path / "new")]) == 2
    assert "is not a run folder" in capsys.readouterr().err and not (tmp_path / "new").exists()
    assert cli(["branch", "--from", str(source), "--out", str(out)]) == 2
    assert "not an empty folder" in capsys.readouterr().err


def copied_run(finished_run, tmp_path) -> tuple[Path, Path]:
    """A copy of the finished run to start new transfer runs in (the shared one stays as the other tests see it)."""
    import shutil

    out, profiles = finished_run
    shutil.copytree(out, tmp_path / "run")
    return tmp_path / "run", profiles


def fixed_states(task: str, robots: list[Path], steps: int = 8) -> dict[str, np.ndarray]:
    """Raw observations of each robot at reset and after a few random actions."""
    states = []
    rng = np.random.default_rng(0)
    for robot in robots:
        env = gym.make(unimal_envs.env_id(task), morphologies=[robot])
        obs, _ = env.reset(seed=3)
        states.append(obs)
        for _ in range(steps):
            obs = env.step(rng.uniform(-1, 1, 24).astype(np.float32))[0]
            states.append(obs)
        env.close()
    return {key: np.stack([s[key] for s in states]) for key in states[0]}


FINETUNED_ARMS = [arm for arm in ARMS if arm not in ("scratch", "modumorph")]


def test_with_learning_rate_zero_a_transfer_run_leaves_every_fine_tuned_arms_actions_exactly_unchanged(finished_run, tmp_path):
    """The inherited observation statistics stay frozen: with no weight update at all, a transfer run
    must not change what the policy does on fixed states (with statistics that go on learning, the
    inputs drift under the frozen weights and the actions move: the issue-26 defect)."""
    from sb3_divmorph.algos.finetune import observation_statistics_frozen
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles, overrides={"transfer.finetune_overrides": {"learning_rate": 0.0}, "transfer.eval_every": 0})
    raw = fixed_states("Escape", profile_robots(profile, "train"))
    for arm in FINETUNED_ARMS:
        run = transfer_run(profile, out, "Escape", arm, 1, progress_bar=False)
        start = run.make_model()
        if run.prepare is not None:
            run.prepare(start)
        before = start.predict(start.get_vec_normalize_env().normalize_obs(raw), deterministic=True)[0]
        trained = run.run()
        normalizer = trained.get_vec_normalize_env()
        assert observation_statistics_frozen(normalizer), arm
        assert normalizer.ret_rms.count > 100, f"{arm}: the reward statistics must learn the new task"
        after = trained.predict(normalizer.normalize_obs(raw), deterministic=True)[0]
        np.testing.assert_array_equal(after, before, err_msg=f"{arm}: actions moved with learning rate 0")


def test_transfer_statistics_left_to_learn_move_a_fine_tuned_arms_actions_at_learning_rate_zero(finished_run, tmp_path):
    """``transfer.freeze_statistics: false`` (a diagnostic) lets the inherited observation statistics learn the novel
    task's states: with no weight update the inputs drift under the weights and the actions move. Broken once: the
    key ignored (statistics frozen) -> the actions hold, fails."""
    from sb3_divmorph.algos.finetune import observation_statistics_frozen
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    overrides = {"transfer.finetune_overrides": {"learning_rate": 0.0}, "transfer.eval_every": 0, "transfer.freeze_statistics": False}
    profile = load_profile("tiny", profiles, overrides=overrides)
    raw = fixed_states("Escape", profile_robots(profile, "train"))
    run = transfer_run(profile, out, "Escape", "closest", 1, progress_bar=False)
    start = run.make_model()
    before = start.predict(start.get_vec_normalize_env().normalize_obs(raw), deterministic=True)[0]
    trained = run.run()
    normalizer = trained.get_vec_normalize_env()
    assert not observation_statistics_frozen(normalizer)
    assert not np.array_equal(trained.predict(normalizer.normalize_obs(raw), deterministic=True)[0], before)


def test_transfer_action_std_changes_what_a_fine_tuned_arm_samples_and_not_its_mean(finished_run, tmp_path):
    """``transfer.action_std: 0.3``: every arm that starts from trained weights samples its actions
    with std 0.3 for the whole run (the checkpoint it saves and resumes from included), while its
    deterministic actions at step 0 are the source's; without the setting they sample with the
    source's 0.9; scratch keeps its own."""
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.training import stage_model
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    raw = fixed_states("Escape", profile_robots(load_profile("tiny", profiles), "train"))

    def sampling_std(model):
        obs = model.policy.obs_to_tensor(model.get_vec_normalize_env().normalize_obs(raw))[0]
        with th.no_grad():
            return model.policy.get_distribution(obs).distribution.stddev

    def mean_action(model):
        return model.predict(model.get_vec_normalize_env().normalize_obs(raw), deterministic=True)[0]

    base = load_profile("tiny", profiles, overrides={"transfer.finetune_overrides": {"learning_rate": 0.0}, "transfer.eval_every": 0})
    narrow = load_profile(
        "tiny",
        profiles,
        overrides={"transfer.finetune_overrides": {"learning_rate": 0.0}, "transfer.eval_every": 0, "transfer.action_std": 0.3},
    )
    for arm in ("closest", "divmorph", "grl"):
        source = transfer_run(base, out, "Escape", arm, 5, progress_bar=False).make_model()  # the same seed: GRL's fresh layers alike
        assert th.allclose(sampling_std(source), th.tensor(0.9)), arm
        run = transfer_run(narrow, out, "Escape", arm, 5, progress_bar=False)
        start = run.make_model()
        assert th.allclose(sampling_std(start), th.tensor(0.3)), arm
        np.testing.assert_array_equal(mean_action(start), mean_action(source), err_msg=arm)
        trained = run.run()  # saved and loaded from its checkpoint on the way
        assert th.allclose(sampling_std(trained), th.tensor(0.3)), arm
        reloaded = type(trained).load(stage_model(run.folder), device="cpu")
        assert th.allclose(reloaded.policy.log_std.exp(), th.tensor(0.3)), arm
    scratch = transfer_run(narrow, out, "Escape", "scratch", 5, progress_bar=False).make_model()
    assert th.allclose(sampling_std(scratch), th.tensor(0.9))
    with pytest.raises(ConfigError, match="transfer.action_std must be a positive number"):
        load_profile("tiny", profiles, overrides={"transfer.action_std": 0})


def test_transfer_curves_roll_out_the_first_eval_robots_of_each_split(finished_run, tmp_path):
    """``transfer.eval_robots: 1``: the evaluation curves (zero-shot, every ``eval_every`` steps, final)
    roll out only the first training and the first novel robot, every episode of each; the evaluation
    stage evaluates the run on the same robots and episodes (so it reuses the last curve point)."""
    from divmorph.pipeline.curves import EVAL_FILE, read_eval
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles, overrides={"transfer.eval_robots": 1, "transfer.eval_episodes": 2})
    run = transfer_run(profile, out, "Escape", "scratch", 3, progress_bar=False)
    run.run()
    rows = read_eval(run.folder / EVAL_FILE)
    assert {row["timesteps"] for row in rows} == {0, 64, 128}
    for split in ("train", "novel"):
        seen = {(row["robot"], row["episode"]) for row in rows if row["split"] == split and row["timesteps"] == 128}
        assert seen == {(profile_robots(profile, split)[0].stem, episode) for episode in (0, 1)}, split
    # the evaluation stage evaluates such a run on its curves' robots and episodes, reusing the last one
    from divmorph.pipeline.evaluate import final_evaluation, transfer_robots_and_episodes

    for split in ("train", "novel"):
        robots, episodes = transfer_robots_and_episodes(profile, split, profile_robots(profile, split), 1)
        assert (robots, episodes) == (profile_robots(profile, split)[:1], 2)
        assert final_evaluation(run.folder, split, robots, episodes) is not None
        assert transfer_robots_and_episodes(profile, split, profile_robots(profile, split), 1, episodes_given=True)[1] == 1
    with pytest.raises(ConfigError, match="eval_robots"):
        load_profile("tiny", profiles, overrides={"transfer.eval_robots": 0})


def test_transfer_curves_sample_robots_across_the_whole_set(finished_run, tmp_path):
    """The curves' robots spread from the first robot of a split to its last, not a prefix of it (robot
    files sort by family: a prefix would stand for one family only)."""
    from divmorph.pipeline.robots import profile_robots, transfer_eval_robots

    _, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles, overrides={"train_robots": 3, "transfer.eval_robots": 2})
    robots = profile_robots(profile, "train")
    assert len(robots) == 3 and transfer_eval_robots(profile, "train") == [robots[0], robots[2]]
    profile = load_profile("tiny", profiles, overrides={"train_robots": 3, "transfer.eval_robots": 5})
    assert transfer_eval_robots(profile, "train") == robots  # more than there are: every robot


def test_the_transfer_figures_name_the_robots_their_curves_roll_out(finished_run, tmp_path):
    """A transfer figure says how many robots and episodes each curve point averages -- those of
    ``transfer.eval_robots``/``eval_episodes``, not the size of the split (the cpu100 figures said
    "mean of 100 robots" over curves of 20 robots x 3 episodes)."""
    from divmorph.pipeline.figures import make_figure

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles, overrides={"train_robots": 3, "transfer.eval_robots": 2, "transfer.eval_episodes": 2})
    assert make_figure(profile, out, "transfer-train") is not None
    with open(out / "report" / "figures" / "transfer-train.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and {(r["robots"], r["episodes"]) for r in rows} == {("2", "2")}


@pytest.mark.parametrize("task", ["Escape", "PointNav", "PushBoxIncline", "ManipulateBox"])
def test_every_arm_sees_its_novel_tasks_inputs_under_one_optimiser_rule(finished_run, tmp_path, task):
    """Perturbing an input the novel task observes (Escape: height map; PointNav: goal; the box
    tasks: box and goal) changes every arm's actions at the start of its run -- MetaMorph→ from an
    FT teacher (no encoders) included -- and every arm's Adam runs with ``transfer.adam_eps``."""
    from divmorph.pipeline.files import atomic_write_json
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import closest_file, transfer_run
    from unimal_envs.tasks import TASKS

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile("tiny", profiles)
    raw = fixed_states(task, profile_robots(profile, "train"), steps=2)
    rng = np.random.default_rng(1)
    starts = [(arm, None) for arm in ARMS if arm != "closest"] + [("closest", "FT"), ("closest", "Patrol")]
    for arm, teacher in starts:
        if teacher is not None:  # force the teacher the closest arm starts from
            atomic_write_json(
                closest_file(out, task, "embedding"),
                {"task": task, "closest": teacher, "by": "embedding", "criterion": "test", "scores": {}},
            )
        run = transfer_run(profile, out, task, arm, 1 if teacher == "Patrol" else 0, progress_bar=False)
        model = run.make_model()
        run.prepare(model)
        assert {g["eps"] for g in model.policy.optimizer.param_groups} == {profile.transfer.adam_eps}, arm
        normalizer = model.get_vec_normalize_env()
        actions = model.predict(normalizer.normalize_obs(raw), deterministic=True)[0]
        for key in TASKS[task].observation_keys:
            changed = {k: v.copy() for k, v in raw.items()}
            changed[key] = changed[key] + rng.normal(0, 1, changed[key].shape).astype(np.float32)
            moved = np.abs(model.predict(normalizer.normalize_obs(changed), deterministic=True)[0] - actions).max()
            assert moved > 1e-6, f"{arm}{f' (from the {teacher} teacher)' if teacher else ''} is blind to {task}'s {key}"


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("observation_statistics", "learning", "transfer.observation_statistics was removed in divmorph 0.2: it always runs 'frozen'"),
        ("compare_scratch", False, r"transfer.compare_scratch was removed in divmorph 0.2: list the arms instead"),
        ("adam_eps", None, r"transfer.adam_eps: None selected a rule retired in divmorph 0.2; today's is 1e-10"),
        ("undiverted_lr_scale", None, r"transfer.undiverted_lr_scale: None selected a rule retired"),
    ],
)
def test_a_profile_asking_for_a_retired_transfer_rule_is_told_what_replaced_it(tmp_path, key, value, message):
    with pytest.raises(ConfigError, match=message):
        load_profile("tiny", write_profiles(tmp_path, **{f"transfer__{key}": value}))


def test_a_run_recorded_before_0_2_is_migrated_once_and_its_retired_rules_are_never_trained_on(finished_run, tmp_path, capsys):
    """A run recorded before the fair-race rules (no keys for them: it ran with learning statistics,
    two Adam eps, ablations at the learngene rate) is not read until migrated; ``divmorph migrate``
    keeps the old record, writes today's keys and the retired rules apart; a command on the run then
    stops at its transfer stage (today's code would go on under other rules) until it is retrained,
    which drops them; a branch reuses the students and races under today's rules."""
    from divmorph.cli import main
    from divmorph.pipeline.branch import branch
    from divmorph.pipeline.provenance import check_and_record, recorded_profile

    out, profiles = copied_run(finished_run, tmp_path)
    record = json.loads((out / "run.json").read_text())
    del record["format"]
    for key in ("adam_eps", "undiverted_lr_scale"):
        del record["configuration"]["transfer"][key]
    record["configuration"]["transfer"]["compare_scratch"] = False
    record["configuration"]["transfer"]["arms"] = None
    old = json.dumps(record)
    (out / "run.json").write_text(old)
    with pytest.raises(ConfigError, match=f"divmorph migrate {out}"):
        recorded_profile(out / "run.json")
    with pytest.raises(ConfigError, match="divmorph migrate"):
        check_and_record(out, load_profile("tiny", profiles), "test")
    assert main(["migrate", str(out), "--check"]) == 1
    assert main(["migrate", str(tmp_path)]) == 0
    assert "transfer.observation_statistics: 'learning'" in capsys.readouterr().out
    assert (out / "run.format-1.json").read_text() == old
    migrated = json.loads((out / "run.json").read_text())
    retired = {key: value for key, value in migrated["retired"].items() if key.startswith("transfer.")}
    assert retired == {"transfer.observation_statistics": "learning", "transfer.adam_eps": None, "transfer.undiverted_lr_scale": None}
    transfer = recorded_profile(out / "run.json").transfer
    assert (transfer.arms, transfer.adam_eps, transfer.undiverted_lr_scale) == (["divmorph"], 1e-10, 1.0)
    assert main(["migrate", str(out)]) == 0 and json.loads((out / "run.json").read_text()) == migrated  # once
    with pytest.raises(ConfigError, match=r"transfer: transfer.observation_statistics: 'learning' \(a rule retired in divmorph 0.2\)"):
        check_and_record(out, recorded_profile(out / "run.json"), "test")
    # a command that trains nothing (evaluate, export, report) goes on reading the finished stages
    assert check_and_record(out, recorded_profile(out / "run.json"), "test", trains=False)["retired"] == migrated["retired"]
    branch(out, tmp_path / "branch", stages=["teachers", "distill"], command="test")
    assert "retired" not in check_and_record(tmp_path / "branch", load_profile("tiny", profiles), "test")
    record = check_and_record(out, load_profile("tiny", profiles), "test", force=True)
    assert "retired" not in record and not (out / "transfer").exists() and list((out / "superseded").iterdir())


def test_a_profile_measuring_heights_from_the_ground_makes_every_env_of_the_run_that_way(tmp_path, monkeypatch):
    """``height_reference: ground`` reaches every env of every stage (teachers, the multi-task
    student's DAgger envs, transfer and its evaluation curves, export, evaluation, HyperDistill):
    a model must always see the heights it was trained on. The student's statistics then hold one
    height distribution for flat FT and the 10-degree Incline (world heights: -12 m apart)."""
    from sb3_divmorph.algos.distillation import load_normalizer
    from unimal_envs.env import UnimalEnv

    made = []
    original = UnimalEnv.__init__

    def recording(self, *args, **kwargs):
        made.append(kwargs.get("height_reference", "world"))
        original(self, *args, **kwargs)

    monkeypatch.setattr(UnimalEnv, "__init__", recording)
    profiles = write_profiles(
        tmp_path,
        height_reference="ground",
        teachers__tasks=["FT", "Incline"],
        transfer__arms=["divmorph", "scratch", "closest"],
        export__tasks=["Incline"],
    )
    out = tmp_path / "run"
    assert cli(["pipeline", "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]) == 0
    assert len(made) > 20 and set(made) == {"ground"}
    heights = load_normalizer(out / "student" / "vecnormalize.pkl").obs_rms["proprioceptive"]
    assert 0 < heights.mean[0, 2] < 1.5 and heights.var[0, 2] ** 0.5 < 0.5  # torso above the ground, FT and Incline alike
    # the batched backend measures heights the same way (tests/test_batched.py): a stage on it gets the setting too
    batched = load_profile("tiny", profiles, overrides={"transfer.env_backend": "batched"})
    if importlib.util.find_spec("mujoco_warp") is not None:
        from divmorph.pipeline.envs import make_vec_env, profile_env_kwargs
        from divmorph.pipeline.robots import profile_robots

        venv = make_vec_env(
            "Unimal-Incline-v0",
            1,
            0,
            100,
            "batched",
            1,
            "cpu",
            1,
            morphologies=profile_robots(batched, "train")[:1],
            **profile_env_kwargs(batched),
        )
        assert venv.get_attr("height_reference") == ["ground"]


def test_task_gates_closest_tells_the_divmorph_arm_the_closest_training_task(finished_run, tmp_path):
    """With ``transfer.task_gates: closest`` the DivMorph arm's envs (training and curves) give the
    closest training task's instruction, so its router (the only reader of the task embedding)
    selects that task's tailors; the other arms keep the novel task's own, and a run folder begun
    under the other setting is refused (break: ignore the setting -> the DivMorph arm reads Escape's)."""
    import dataclasses

    from divmorph.pipeline.branch import branch
    from divmorph.pipeline.evaluate import run_instruction
    from divmorph.pipeline.folders import transfer_folder
    from divmorph.pipeline.transfer import closest_task, transfer_run
    from unimal_envs.instructions import INSTRUCTIONS, shipped_embeddings

    source, profiles = finished_run
    out = tmp_path / "run"
    branch(source, out)
    base = load_profile("tiny", profiles)
    profile = dataclasses.replace(base, transfer=dataclasses.replace(base.transfer, task_gates="closest"))
    closest = closest_task(profile, out, "Escape")["closest"]
    embeddings = shipped_embeddings()

    def told(arm: str) -> np.ndarray:
        venv = transfer_run(profile, out, "Escape", arm, progress_bar=False).make_env()
        obs = venv.reset()
        venv.close()
        return obs["task_embedding"][0]

    assert closest != "Escape" and np.allclose(told("divmorph"), embeddings[closest], atol=1e-5)
    assert np.allclose(told("divmorph-finetuned"), embeddings[closest], atol=1e-5)  # it starts from the same gates
    assert np.allclose(told("closest"), embeddings["Escape"], atol=1e-5)
    # the evaluation stage plays the run with the instruction it trained with
    assert run_instruction(base, transfer_folder(out, "Escape", "divmorph", 0), "Escape") == INSTRUCTIONS[closest]
    assert run_instruction(base, transfer_folder(out, "Escape", "closest", 0), "Escape") is None
    with pytest.raises(ConfigError, match="built-in instruction"):
        transfer_run(base, out, "Escape", "divmorph", progress_bar=False)


def test_the_fully_finetuned_divmorph_arm_moves_its_gates_and_the_divmorph_arm_keeps_them(finished_run):
    """``divmorph-finetuned`` fine-tunes the DivMorph student like MetaMorph⚗ (every weight), so its
    router -- and with it the gates -- moves under PPO, while the DivMorph arm's stays exactly as
    distilled (break: give ``divmorph-finetuned`` ``divmorph_transfer=True`` -> its router is frozen)."""
    from divmorph.pipeline.folders import student_folder, transfer_folder
    from divmorph.pipeline.training import stage_model

    out, _ = finished_run
    distilled = PPO.load(stage_model(student_folder(out, "divmorph")), device="cpu").policy.router

    def router_change(arm: str) -> float:
        router = PPO.load(stage_model(transfer_folder(out, "Escape", arm, 0)), device="cpu").policy.router
        return max(float((a - b).detach().abs().max()) for a, b in zip(distilled.parameters(), router.parameters()))

    assert router_change("divmorph") == 0.0
    assert router_change("divmorph-finetuned") > 0.0


def test_a_loaded_transfer_run_plays_with_the_instruction_it_trained_with(finished_run, tmp_path):
    """``load_pretrained`` (and so ``divmorph record``) of a transfer run folder, ``seed-<n>`` ones
    included, knows its task and gives its envs the instruction the run trained with: the one
    ``source.json`` records (``task_gates: closest``); on another task that task's own (break: drop
    the recorded instruction in ``find_model`` -> the env reads Escape's)."""
    import json

    from divmorph.pipeline.training import has_model
    from divmorph.pretrained import load_pretrained
    from unimal_envs.instructions import INSTRUCTIONS, shipped_embeddings

    out, _ = copied_run(finished_run, tmp_path)
    folder = out / "transfer" / "Escape" / "divmorph" / "seed-0"
    assert has_model(folder)
    record = folder / "source.json"
    recorded = json.loads(record.read_text())
    embeddings = shipped_embeddings()

    def embedding(model, task=None):
        env = model.make_env(model.robots[:1], task=task)
        obs = env.reset(seed=0)[0]
        env.close()
        return obs["task_embedding"]

    record.write_text(json.dumps({k: v for k, v in recorded.items() if k != "instruction"}))
    plain = load_pretrained(folder)
    assert plain.env_id == "Unimal-Escape-v0"
    assert np.allclose(embedding(plain), embeddings["Escape"], atol=1e-5)
    record.write_text(json.dumps({**recorded, "instruction": INSTRUCTIONS["Patrol"]}))
    told = load_pretrained(folder)
    assert told.env_kwargs["instruction"] == INSTRUCTIONS["Patrol"]
    assert np.allclose(embedding(told), embeddings["Patrol"], atol=1e-5)
    assert np.allclose(embedding(told, task="FT"), embeddings["FT"], atol=1e-5)


def test_an_adapter_transfer_run_starts_as_the_student_learns_in_its_adapters_and_resumes_with_them(finished_run, tmp_path):
    """``transfer.recipe: adapter`` through the pipeline: the run's first model acts as the fixed-gate arm's
    (zero-initialised adapters), training moves its actions while every factor stays, and the finished run
    loads again with its trained adapters (break: leave ``adapter_rank`` out of ``finetuned_model``'s
    kwargs -> the recipe finds no adapters; load with ``strict=True`` -> the source does not fit)."""
    from sb3_divmorph.algos.finetune import adapter_parameters
    from sb3_divmorph.nn.layers import FactorizedLinear
    from divmorph.pipeline.robots import profile_robots
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    plain = load_profile("tiny", profiles, overrides={"transfer.eval_every": 0})
    adapted = load_profile("tiny", profiles, overrides={"transfer.eval_every": 0, "transfer.recipe": "adapter", "transfer.adapter_rank": 2})
    raw = fixed_states("Escape", profile_robots(plain, "train"))

    def actions(model):
        return model.predict(model.get_vec_normalize_env().normalize_obs(raw), deterministic=True)[0]

    student = transfer_run(plain, out, "Escape", "divmorph", 3, progress_bar=False).make_model()
    run = transfer_run(adapted, out, "Escape", "divmorph", 4, progress_bar=False)
    start = run.make_model()
    run.prepare(start)
    assert adapter_parameters(start.policy) and start.policy_kwargs["adapter_rank"] == 2
    np.testing.assert_allclose(actions(start), actions(student), atol=1e-5)
    factors = {
        name: p.detach().clone()
        for name, p in start.policy.named_parameters()
        if name.startswith("mlp_extractor.policy_net") and "adapter" not in name
    }
    trained = run.run()
    assert np.abs(actions(trained) - actions(student)).max() > 1e-4, "the adapters learnt nothing"
    for name, p in trained.policy.named_parameters():
        if name in factors:
            assert th.equal(p.detach(), factors[name]), name
    loaded = transfer_run(adapted, out, "Escape", "divmorph", 4, progress_bar=False).run()  # finished: loaded, not retrained
    assert any(isinstance(m, FactorizedLinear) and m.adapter_rank == 2 for m in loaded.policy.modules())
    np.testing.assert_array_equal(actions(loaded), actions(trained))


def test_the_transfer_students_learngenes_keep_the_papers_share_of_every_diverted_layer():
    """The ``cpu100-transfer`` profile's student keeps at least 75% of each diverted layer's rank as
    learngenes (the ``paper`` preset: 96 of 128) and distils with a load-balanced router; cpu100's own
    student keeps 8 of 32, which is why transfer does not start from it (break: set the profile's
    tailors back to 12 + 12 -> fails)."""
    from stable_baselines3 import PPO

    from divmorph.pipeline.students import STUDENTS
    from sb3_divmorph.nn.layers import FactorizedLinear
    from unimal_envs.morphology.loader import morphology_files

    env = gym.make("Unimal-MultiTask-v1", morphologies=morphology_files("train")[:2])

    def learngene_shares(profile_name: str) -> list[float]:
        kwargs = STUDENTS["divmorph"].kwargs(load_profile(profile_name))
        policy = PPO("DivMorphPolicy", env, policy_kwargs=kwargs, n_steps=64, device="cpu").policy
        layers = [m for m in policy.modules() if isinstance(m, FactorizedLinear) and m.n_tailors > 0]
        assert layers
        return [m.n_learngenes / m.rank for m in layers]

    assert min(learngene_shares("cpu100-transfer")) >= 0.75
    assert max(learngene_shares("cpu100")) < 0.75
    assert load_profile("cpu100-transfer").distill.load_balance > 0
    # the transfer student's profile differs from cpu100's in the student and its distillation only
    same = {k: v for k, v in dataclasses.asdict(load_profile("cpu100")).items() if k not in ("name", "student", "distill")}
    assert same == {k: v for k, v in dataclasses.asdict(load_profile("cpu100-transfer")).items() if k not in ("name", "student", "distill")}


@pytest.mark.parametrize("train_robots, trained", [("all", 2), ("eval", 1)])
def test_transfer_train_robots_eval_trains_only_on_the_robots_the_curves_read(finished_run, tmp_path, train_robots, trained):
    from divmorph.pipeline.robots import transfer_eval_robots
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile(
        "tiny", profiles, overrides={"transfer.train_robots": train_robots, "transfer.eval_robots": 1, "transfer.eval_every": 0}
    )
    run = transfer_run(profile, out, "Escape", "scratch", 3, progress_bar=False)
    model = run.make_model()
    robots = {Path(name).stem for name in model.get_env().get_attr("morphology_names", indices=[0])[0]}
    assert len(robots) == trained
    if train_robots == "eval":
        assert robots == {p.stem for p in transfer_eval_robots(profile, "train")}


@pytest.mark.parametrize("splits", [["train"], ["train", "novel"]])
def test_transfer_eval_splits_are_the_splits_the_curves_roll_out(finished_run, tmp_path, splits):
    from divmorph.pipeline.transfer import transfer_run

    out, profiles = copied_run(finished_run, tmp_path)
    profile = load_profile(
        "tiny", profiles, overrides={"transfer.eval_splits": splits, "transfer.eval_every": 64, "transfer.eval_episodes": 1}
    )
    run = transfer_run(profile, out, "Escape", "scratch", 3, progress_bar=False)
    run.run()
    with open(out / "transfer" / "Escape" / "scratch" / "seed-3" / "eval.csv") as f:
        assert {row["split"] for row in csv.DictReader(f)} == set(splits)


def test_transfer_eval_splits_must_name_known_splits_once(tmp_path):
    profiles = write_profiles(tmp_path)
    for bad in ([], ["train", "train"], ["held-out"]):
        with pytest.raises(ConfigError, match="eval_splits"):
            load_profile("tiny", profiles, overrides={"transfer.eval_splits": bad})
