"""Grids of independent runs: the Ray backend (resumes after a killed run), and bad input for the arms."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_pipeline import write_profiles

from divmorph.cli import main as cli
from divmorph.pipeline.config import ConfigError, load_profile
from divmorph.pipeline.files import read_done
from divmorph.pipeline.training import latest_checkpoint
from unimal_envs.instructions import INSTRUCTIONS


def _base(profiles: Path, out: Path) -> list[str]:
    return ["--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]


def test_bad_arms_seeds_and_missing_stages_give_clear_errors(tmp_path, capsys):
    base = _base(write_profiles(tmp_path), tmp_path / "empty")
    assert cli(["transfer", *base, "--arms", "divmorph,bogus"]) == 2
    err = capsys.readouterr().err
    assert "unknown arm(s) ['bogus']" in err and "'no-orthogonality'" in err and "'grl'" in err
    assert cli(["transfer", *base, "--arms", "scratch", "--seeds", "0", "1", "0"]) == 2
    assert "seed(s) [0] given twice" in capsys.readouterr().err
    assert cli(["transfer", *base, "--arms", "scratch,scratch"]) == 2
    assert "given twice" in capsys.readouterr().err
    for arm, stage in (
        ("distilled", "divmorph distill"),
        ("no-kdiv-decoder", "divmorph distill"),
        ("closest", "divmorph teachers"),
        ("grl", "divmorph grl"),
    ):
        assert cli(["transfer", *base, "--arms", arm]) == 2
        err = capsys.readouterr().err
        assert stage in err, (arm, err)
    assert not (tmp_path / "empty" / "transfer").exists() or not list((tmp_path / "empty" / "transfer").glob("*/*/seed-*"))
    bad = tmp_path / "bad"
    bad.mkdir()
    with pytest.raises(ConfigError, match=r"unknown arm\(s\) \['ablation'\]; valid arms"):
        load_profile("tiny", write_profiles(bad, transfer__arms=["divmorph", "ablation"]))
    with pytest.raises(ConfigError, match="given twice"):
        load_profile("tiny", write_profiles(bad, transfer__seeds=[1, 1]))
    assert cli(["transfer", *base, "--arms", "scratch", "--cpus-per-run", "2"]) == 2
    assert "need --backend ray" in capsys.readouterr().err
    assert cli(["figure", "fig9", *base]) == 2
    assert "unknown figure 'fig9'; figures: ['transfer-train'" in capsys.readouterr().err
    assert cli(["figure", "ablation", *base]) == 2
    assert "no such run folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir(exist_ok=True)
    assert cli(["figure", "ablation", *base]) == 2
    assert "no data for figure 'ablation'" in capsys.readouterr().err


def _ray_is_connected() -> bool:
    ray = sys.modules.get("ray")
    return ray is not None and ray.is_initialized()


def test_a_ray_address_that_does_not_answer_fails_fast(tmp_path, capsys):
    base = _base(write_profiles(tmp_path), tmp_path / "run")
    # the address is probed before Ray connects: the error, not a hang in ray.init (what "fast" stands for)
    assert cli(["transfer", *base, "--arms", "scratch", "--backend", "ray", "--address", "127.0.0.1:9"]) == 2
    assert "Ray address '127.0.0.1:9' does not answer" in capsys.readouterr().err
    assert not _ray_is_connected()
    assert cli(["transfer", *base, "--arms", "scratch", "--backend", "ray", "--address", "nonsense"]) == 2
    assert "is not host:port" in capsys.readouterr().err


def test_closest_by_embedding_follows_the_instruction(tmp_path):
    from divmorph.pipeline.transfer import closest_task

    for twin in ("Patrol", "FT"):
        out = tmp_path / f"like-{twin}"
        out.mkdir()
        profile = load_profile("tiny", write_profiles(out, transfer__instructions={"Escape": INSTRUCTIONS[twin]}))
        choice = closest_task(profile, out, "Escape")
        assert choice["closest"] == twin and choice["scores"][twin] == pytest.approx(1.0, abs=1e-5)
        # written once: every seed (and a Ray worker) reads the same choice
        assert json.loads((out / "transfer" / "Escape" / "closest-by-embedding.json").read_text()) == choice


def _steps(folder: Path) -> int:
    try:
        return json.loads((folder / "checkpoints" / "latest.json").read_text())["num_timesteps"]
    except (OSError, ValueError):
        return 0


def test_a_ray_grid_resumes_after_one_run_is_killed(tmp_path):
    pytest.importorskip("ray")
    profiles = write_profiles(tmp_path, transfer__n_timesteps=1536, transfer__checkpoint_every=256, transfer__eval_every=0)
    out = tmp_path / "run"
    command = [
        sys.executable,
        "-m",
        "divmorph.cli",
        "transfer",
        "--task",
        "Escape",
        "--arms",
        "scratch",
        "--seeds",
        "0",
        "1",
        "--backend",
        "ray",
        "--cpus-per-run",
        "1",
        "--ray-cpus",
        "2",
        *_base(profiles, out),
    ]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")])}
    victim, survivor = out / "transfer" / "Escape" / "scratch" / "seed-1", out / "transfer" / "Escape" / "scratch" / "seed-0"
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    deadline = time.time() + 600  # Ray's start and the first checkpoint take minutes on a loaded machine
    while time.time() < deadline and (_steps(victim) < 256 or not (victim / "running.json").is_file()):
        time.sleep(0.1)
    assert _steps(victim) >= 256, "the run to kill never wrote a checkpoint"
    worker = json.loads((victim / "running.json").read_text())["pid"]
    assert worker != process.pid  # a Ray worker, not the driver
    os.kill(worker, signal.SIGKILL)
    output, _ = process.communicate(timeout=300)
    saved = _steps(victim)
    # the killed run is reported, the other one finished
    assert process.returncode == 1, output
    assert "FAILED transfer Escape scratch seed 1" in output
    assert read_done(survivor)["num_timesteps"] == 1536
    assert not (victim / "done.json").exists() and latest_checkpoint(victim / "checkpoints") is not None

    stamp = (survivor / "model.zip").stat().st_mtime_ns
    rerun = subprocess.run(
        command, capture_output=True, text=True, env=env, timeout=600
    )  # Ray's start alone can take minutes on a loaded machine
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "1 trained, 1 already done, 0 failed" in rerun.stdout
    assert (survivor / "model.zip").stat().st_mtime_ns == stamp  # skipped, not retrained
    assert read_done(victim)["num_timesteps"] == 1536
    import csv

    with open(victim / "logs" / "run-1" / "progress.csv") as f:
        resumed = [int(float(row["time/total_timesteps"])) for row in csv.DictReader(f)]
    assert saved < resumed[0] <= saved + 256  # from the last checkpoint, not from zero


def test_a_transfer_run_from_before_seeds_is_seed_0(tmp_path):
    from divmorph.pipeline.transfer import transfer_folder

    legacy = tmp_path / "transfer" / "Escape" / "divmorph"
    assert transfer_folder(tmp_path, "Escape", "divmorph", 0) == legacy / "seed-0"
    (legacy / "checkpoints").mkdir(parents=True)  # an interrupted run of the old layout resumes where it is
    assert transfer_folder(tmp_path, "Escape", "divmorph", 0) == legacy
    assert transfer_folder(tmp_path, "Escape", "divmorph", 1) == legacy / "seed-1"
