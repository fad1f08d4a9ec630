"""Evaluate a teacher checkpoint brought back from the GPU machine the way the cpu100 run's evaluation
stage rolls out its teachers, and compare it with that run's FT teacher robot by robot.

Both sides go through the same code: :func:`~divmorph.pipeline.curves.evaluate_model` with single
C envs, deterministic actions, ``--episodes`` episodes per robot of at most 1,000 steps, seed 0 (the
profile's seed), on the 100 official training robots and the 100 novel robots. The cpu100 side is read
from ``results/cpu100/evaluate/returns.csv(.gz)`` (rows ``teacher`` / ``teacher-untrained``), which
that stage wrote with these same settings.

    python results/gpu-h200/gpu_teacher_eval.py --checkpoint /path/to/step-000012134400 \
        --out results/gpu-h200/session-3/returns.csv.gz        # ~13 min per split on one core

A checkpoint folder holds ``model.zip`` and ``vecnormalize.pkl`` (the run's ``checkpoints/step-*``).
With ``--out`` already written, only the comparison is printed again (``--summary`` writes it to a file).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import time
from pathlib import Path

import numpy as np
import torch

from divmorph.pipeline.config import load_profile
from divmorph.pipeline.curves import evaluate_model
from divmorph.pipeline.metrics import robot_interval
from divmorph.pipeline.files import read_csv_rows
from divmorph.pipeline.robots import profile_robots

ROOT = Path(__file__).resolve().parents[2]
COLUMNS = ["model", "task", "split", "morphology", "episode", "return", "length"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, help="checkpoint folder (model.zip + vecnormalize.pkl); not needed once --out exists")
    parser.add_argument("--label", default="gpu-teacher", help="model name in the rows")
    parser.add_argument("--task", default="FT")
    parser.add_argument("--episodes", type=int, default=3, help="deterministic episodes per robot (the cpu100 evaluation's)")
    parser.add_argument("--run", type=Path, default=ROOT / "results" / "cpu100", help="the CPU run to compare with")
    parser.add_argument("--out", type=Path, required=True, help="rows of this evaluation (.csv or .csv.gz)")
    parser.add_argument("--summary", type=Path, help="also write the comparison (markdown) here")
    args = parser.parse_args()

    if not args.out.exists():
        if args.checkpoint is None:
            parser.error(f"{args.out} does not exist yet: give --checkpoint to evaluate")
        torch.set_num_threads(1)
        profile = load_profile("cpu100")
        rows = []
        for split in ("train", "novel"):
            start = time.time()
            # the GPU run used the default height reference ("world"); on FT's flat floor it is the ground's
            found = evaluate_model(
                args.checkpoint, args.task, profile_robots(profile, split), args.episodes, 1000, profile.seed, env_kwargs={}
            )
            rows += [{"model": args.label, "task": args.task, "split": split, **row} for row in found]
            print(f"{split}: {len(found)} episodes in {time.time() - start:.0f} s", flush=True)
        write_rows(args.out, rows)
    # the run's rows: its plain returns.csv or the packed twin, whichever read_csv_rows takes
    table = comparison(read_csv_rows(args.out), read_csv_rows(args.run / "evaluate" / "returns.csv"), args.task)
    print(table)
    if args.summary:
        args.summary.write_text(table + "\n")


def comparison(ours: list[dict[str, str]], run: list[dict[str, str]], task: str) -> str:
    """A markdown table: per split, the mean over robots [95% bootstrap CI] of this model, the run's
    teacher and its untrained policy, and the paired difference with the run's teacher."""
    lines = [
        "| split | this model | cpu100 teacher | cpu100 untrained | this - cpu100 teacher [paired 95% CI] | robots better |",
        "|---|---|---|---|---|---|",
    ]
    for split in ("train", "novel"):
        mine = per_robot(ours, split, task, {r["model"] for r in ours})
        teacher = per_robot(run, split, task, {"teacher"})
        untrained = per_robot(run, split, task, {"teacher-untrained"})
        robots = sorted(set(mine) & set(teacher))
        if not robots:
            continue
        a = np.array([mine[r] for r in robots])
        b = np.array([teacher[r] for r in robots])
        u = np.array([untrained[r] for r in robots if r in untrained])
        lines.append(
            f"| {split} ({len(robots)} robots) | {fmt(a)} (median {np.median(a):.0f}) | {fmt(b)} (median {np.median(b):.0f}) "
            f"| {fmt(u) if len(u) else '-'} | {fmt(a - b, sign=True)} | {(a > b).sum()} of {len(robots)} |"
        )
    return "\n".join(lines)


def per_robot(rows: list[dict[str, str]], split: str, task: str, models: set[str]) -> dict[str, float]:
    """Mean return per robot of the rows of ``models`` on ``task`` and ``split``."""
    returns: dict[str, list[float]] = {}
    for row in rows:
        if row["model"] in models and row["task"] == task and row["split"] == split:
            returns.setdefault(row["morphology"], []).append(float(row["return"]))
    return {robot: float(np.mean(values)) for robot, values in returns.items()}


def fmt(values: np.ndarray, sign: bool = False) -> str:
    """``mean [low, high]``: the 95% bootstrap interval over robots the run's report uses."""
    low, high = robot_interval(values)
    f = "{:+.0f}" if sign else "{:.0f}"
    return f"{f.format(values.mean())} [{f.format(low)}, {f.format(high)}]"


def write_rows(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "wt", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
