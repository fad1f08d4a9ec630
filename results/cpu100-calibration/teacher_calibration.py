"""Which teacher settings suit a profile? Trained-vs-untrained returns of calibration teachers, on training robots only.

Each ``--runs`` folder is a ``divmorph teachers --task TASK`` run (one teacher; the settings under
test -- learning rate, width, budget -- set with ``--set`` on its command line and recorded in its
``run.json``). For each run this script rolls out, deterministically and ``--episodes`` times on
every one of the run's *training* robots, the trained teacher and the same policy before training
(the run's initial weights and fresh normaliser: :func:`~divmorph.pipeline.evaluate.evaluate_untrained_teacher`),
and reads the run's training curve and wall time. Novel robots are never rolled out: settings are
chosen without looking at them.

Writes ``<out>/README.md`` (mean return with a 95% bootstrap interval over robots, median, robots
above thresholds, throughput), ``<out>/returns.csv.gz`` (one row per run, model, robot and episode) and
``<out>/training_curves.png`` with its numbers in ``<out>/curves.csv.gz`` (the mean return of the episodes finished in each rollout -- stochastic
actions, so below the deterministic return -- against env steps).

    divmorph teachers --profile cpu100 --out results/cpu100-calibration/w32 --task FT --no-progress
    python results/cpu100-calibration/teacher_calibration.py --runs results/cpu100-calibration/w32 results/cpu100-calibration/w64 \\
        --out results/cpu100-calibration
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch as th  # noqa: E402

from divmorph.pipeline.curves import evaluate_model  # noqa: E402
from divmorph.pipeline.evaluate import evaluate_untrained_teacher  # noqa: E402
from divmorph.pipeline.folders import teacher_folder  # noqa: E402
from divmorph.pipeline.metrics import robot_interval  # noqa: E402
from divmorph.pipeline.provenance import RECORD, recorded_profile  # noqa: E402
from divmorph.pipeline.envs import profile_env_kwargs  # noqa: E402
from divmorph.pipeline.files import is_done, read_progress  # noqa: E402
from divmorph.pipeline.robots import profile_robots  # noqa: E402

#: Returns a reader of the table asks about: "walks at all" and "walks well" on FT.
THRESHOLDS = (500, 1000)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", type=Path, required=True, help="teacher run folders (one finished teacher each)")
    parser.add_argument("--task", default="FT", help="the teachers' task (default FT)")
    parser.add_argument("--episodes", type=int, default=1, help="deterministic episodes per training robot (default 1)")
    parser.add_argument("--out", type=Path, required=True, help="folder for README.md, returns.csv.gz and training_curves.png")
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)

    rows, summaries, curves = [], [], {}
    for run in args.runs:
        folder = teacher_folder(run, args.task)
        if not is_done(folder):
            raise SystemExit(f"{folder} has no finished teacher (no done.json); finish it with the command in {run / RECORD}")
        profile = recorded_profile(run / RECORD)
        robots = profile_robots(profile, "train")
        started = time.time()
        trained = evaluate_model(
            folder, args.task, robots, args.episodes, profile.max_episode_steps, profile.seed, env_kwargs=profile_env_kwargs(profile)
        )
        untrained = evaluate_untrained_teacher(profile, run, args.task, robots, args.episodes, profile.seed)
        print(f"[calibration] {run}: evaluated {len(robots)} robots x {args.episodes} episodes twice in {time.time() - started:.0f} s")
        for model, results in (("teacher", trained), ("teacher-untrained", untrained)):
            rows += [{"run": run.name, "model": model, **r} for r in results]
        progress = read_progress(folder)
        steps, wall = progress["time/total_timesteps"], progress["time/time_elapsed"]
        curves[run.name] = (steps, progress["rollout/ep_rew_mean"])
        summaries.append(_summary(run, profile, trained, untrained, float(steps[-1]), _wall_time(wall)))

    pd.DataFrame(rows).to_csv(args.out / "returns.csv.gz", index=False)  # gzip: the tracked tree stays small
    # the curves of the figure, small enough to keep in the tree (a run's logs are not)
    pd.concat(
        [pd.DataFrame({"run": name, "env_steps": steps, "ep_rew_mean": returns}) for name, (steps, returns) in curves.items()]
    ).to_csv(args.out / "curves.csv.gz", index=False, float_format="%.2f")
    _plot(curves, args.task, args.out / "training_curves.png")
    (args.out / "README.md").write_text(_report(args, summaries))
    print((args.out / "README.md").read_text())


def _summary(run: Path, profile, trained: list[dict], untrained: list[dict], steps: float, wall: float) -> dict:
    """One table row: the run's settings and its per-robot mean returns (trained and untrained)."""
    per_robot = pd.DataFrame(trained).groupby("morphology")["return"].mean().to_numpy()
    before = pd.DataFrame(untrained).groupby("morphology")["return"].mean().to_numpy()
    lo, hi = robot_interval(per_robot)
    b_lo, b_hi = robot_interval(before)
    teachers = profile.teachers
    return {
        "run": run.name,
        "policy_kwargs": teachers.policy_kwargs,
        "learning_rate": teachers.overrides.get("learning_rate", "zoo"),
        "steps": steps,
        "robots": len(per_robot),
        "mean": per_robot.mean(),
        "ci": (lo, hi),
        "median": float(np.median(per_robot)),
        "above": [int((per_robot >= t).sum()) for t in THRESHOLDS],
        "untrained": before.mean(),
        "untrained_ci": (b_lo, b_hi),
        "wall": wall,
    }


def _wall_time(elapsed: np.ndarray) -> float:
    """Training seconds over every attempt of a resumed run (each attempt's clock restarts at 0)."""
    restarts = np.flatnonzero(np.diff(elapsed) < 0)
    return float(sum(elapsed[i] for i in restarts) + elapsed[-1])


def _plot(curves: dict[str, tuple[np.ndarray, np.ndarray]], task: str, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for name, (steps, returns) in curves.items():
        ax.plot(steps / 1e6, returns, label=name)
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel(f"{task} episode return (stochastic, training rollouts)")
    ax.set_title("Calibration teachers: mean return of finished episodes")
    ax.legend(title="run")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _report(args: argparse.Namespace, summaries: list[dict]) -> str:
    lines = [
        f"# Teacher calibration on {args.task}: training robots only",
        "",
        f"Deterministic return of each calibration teacher on every training robot ({args.episodes} episode(s) per robot), "
        "next to the same policy before training; 95% bootstrap intervals over robots. No novel robot was rolled out.",
        "",
        "```bash",
        f"python results/cpu100-calibration/teacher_calibration.py --runs {' '.join(str(r) for r in args.runs)} --task {args.task} "
        f"--episodes {args.episodes} --out {args.out}",
        "```",
        "",
        "| run | policy_kwargs | learning rate | env steps | robots | mean return [95% CI] | median | "
        + " | ".join(f"robots >= {t}" for t in THRESHOLDS)
        + " | untrained mean [95% CI] | training wall time (s) | env steps/s |",
        "|---|---|---|---:|---:|---|---:|" + "---:|" * len(THRESHOLDS) + "---|---:|---:|",
    ]
    for s in summaries:
        lines.append(
            f"| {s['run']} | `{s['policy_kwargs']}` | {s['learning_rate']} | {s['steps']:,.0f} | {s['robots']} | "
            f"{s['mean']:.0f} [{s['ci'][0]:.0f}, {s['ci'][1]:.0f}] | {s['median']:.0f} | "
            + " | ".join(str(n) for n in s["above"])
            + f" | {s['untrained']:.0f} [{s['untrained_ci'][0]:.0f}, {s['untrained_ci'][1]:.0f}] | {s['wall']:.0f} | {s['steps'] / s['wall']:.0f} |"
        )
    lines += [
        "",
        "![training curves](training_curves.png)",
        "",
        f"Written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.machine()} ({os.cpu_count()} cores), "
        f"torch {th.__version__}, 1 thread per process. Per-robot returns: `returns.csv.gz`; the curves' numbers: `curves.csv.gz`.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
