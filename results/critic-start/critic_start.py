"""Which critic should a fine-tuned student start with? A calibration on a *training* task (issue 26, item 4).

A distilled student arrives at a new task with a critic that never learnt anything (DAgger distils
the actor's means only), so PPO's first updates follow the advantages of an arbitrary value
function. The race's rule for every arm that starts from trained weights is one of: no critic
warm-up (the race of ``results/cpu-race``), a critic warm-up (``transfer.critic_warmup``: the
first N env steps train the critic only), or a critic that learns at a multiple of the fine-tuned
actor's rate (``transfer.critic_lr_scale``: 10 x lin_1e-4 = scratch's lin_1e-3), or both. This script
measures which is better where the answer
is known in advance -- on the training task FT, whose skill the students already have, so any
fall of the return during fine-tuning is damage, not exploration -- never on the novel tasks.

For each variant it branches the source run (``divmorph branch``: its students, read-only) into
``<out>/<variant>/`` and runs the race's own transfer runs (:func:`divmorph.pipeline.transfer.transfer_run`,
``calibration=True``) of the ``divmorph`` and ``distilled`` arms on FT, with the race's settings
(fine-tuning at lin_1e-4, frozen inherited observation statistics, Adam eps 1e-10), 3 seeds,
evaluated every ``--eval-every`` steps on the training robots (3 deterministic episodes each).
Runs resume; finished ones are skipped. Writes ``<out>/README.md`` (and ``eval.csv`` per run).

    python results/critic-start/critic_start.py                      # ~70 min on one core
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch as th

from divmorph.pipeline.branch import branch
from divmorph.pipeline.folders import transfer_folder
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.files import log_file, read_progress
from divmorph.pipeline.metrics import paired_run_interval, run_interval
from divmorph.pipeline.transfer import transfer_run

ARMS = ("divmorph", "distilled")


def variants(warmup: int, critic_scale: float) -> dict[str, dict[str, float]]:
    """``{variant folder: its transfer settings}`` (the first is the baseline of the paired differences)."""
    return {
        "no-warmup": {"transfer.critic_warmup": 0},
        f"warmup-{warmup // 1000}k": {"transfer.critic_warmup": warmup},
        f"critic-{critic_scale:g}x": {"transfer.critic_warmup": 0, "transfer.critic_lr_scale": critic_scale},
        f"warmup-{warmup // 1000}k+critic-{critic_scale:g}x": {"transfer.critic_warmup": warmup, "transfer.critic_lr_scale": critic_scale},
    }


def by_run(values: pd.Series) -> np.ndarray:
    """Seeds x robots (robots every seed has) from values indexed by (robot, seed): an interval resamples the
    training runs and the robots within them (a run's robots share its policy: not independent draws)."""
    return values.unstack("robot").dropna(axis=1).to_numpy()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", default="results/cpu", help="the run whose students are fine-tuned")
    parser.add_argument("--out", type=Path, default=Path("results/critic-start"))
    parser.add_argument("--task", default="FT", help="a training task")
    parser.add_argument("--steps", type=int, default=40_000, help="env steps per run")
    parser.add_argument("--eval-every", type=int, default=20_000)
    parser.add_argument("--warmup", type=int, default=16_384, help="critic-only env steps of the warm-up variant")
    parser.add_argument("--critic-scale", type=float, default=10.0, help="critic learning-rate multiple of the third variant")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    start = time.time()
    for variant, settings in variants(args.warmup, args.critic_scale).items():
        out = args.out / variant
        if not (out / "run.json").exists():
            branch(Path(args.source), out, ("distill",), command="python results/critic-start/critic_start.py")
        profile = recorded_profile(
            out / "run.json",
            {
                "transfer.n_timesteps": args.steps,
                "transfer.eval_every": args.eval_every,
                "transfer.checkpoint_every": args.eval_every,
                "transfer.eval_episodes": 3,
                "transfer.finetune_overrides": {"learning_rate": "lin_1e-4"},
                **settings,
            },
        )
        for arm in ARMS:
            for seed in args.seeds:
                print(f"[critic-start] {variant}: {arm} seed {seed} on {args.task}", flush=True)
                transfer_run(profile, out, args.task, arm, seed, progress_bar=False, calibration=True).run()
    write_report(args, time.time() - start)


def write_report(args: argparse.Namespace, seconds: float) -> None:
    """``<out>/README.md``: mean return on the training robots at each evaluation, per arm and variant, with CIs."""
    rows = []
    names = list(variants(args.warmup, args.critic_scale))
    for variant in names:
        for arm in ARMS:
            for seed in args.seeds:
                frame = pd.read_csv(log_file(transfer_folder(args.out / variant, args.task, arm, seed) / "eval.csv"))
                frame = frame[frame.split == "train"].groupby(["timesteps", "robot"], as_index=False)["return"].mean()
                rows.append(frame.assign(variant=variant, arm=arm, seed=seed))
    data = pd.concat(rows)
    data = data[data.timesteps % args.eval_every == 0]  # the end-of-run evaluation repeats the last scheduled one
    steps = sorted(data.timesteps.unique())
    lines = [
        f"# The critic a fine-tuned student starts with: a calibration on the training task {args.task}",
        "",
        f"`python results/critic-start/critic_start.py --source {args.source} --task {args.task} --steps {args.steps} "
        f"--eval-every {args.eval_every} --warmup {args.warmup} --critic-scale {args.critic_scale:g} "
        f"--seeds {' '.join(map(str, args.seeds))}`; "
        f"machine: {platform.node()} ({platform.machine()}, 1 torch thread, beside other jobs); "
        f"{time.strftime('%Y-%m-%d')}; {seconds / 60:.0f} min for the runs this call trained.",
        "",
        "Mean deterministic return on the run's training robots (3 episodes per robot, averaged per robot), mean over "
        "robots x seeds with a 95% bootstrap interval over training runs (seeds) and robots; step 0 is the student before any update (the same for both variants "
        "but for the seed's evaluation noise).",
        "",
        "| arm | critic | "
        + " | ".join(f"{s / 1000:.0f}k" for s in steps)
        + f" | change 0 -> last | last minus {names[0]}'s (paired) | critic's explained variance |",
        "|---|---|" + "---|" * len(steps) + "---|---|---|",
    ]
    for arm in ARMS:
        for variant in names:
            cells = []
            for s in steps:
                values = by_run(
                    data[(data.arm == arm) & (data.variant == variant) & (data.timesteps == s)].set_index(["robot", "seed"])["return"]
                )
                low, high = run_interval(values)
                cells.append(f"{values.mean():.1f} [{low:.1f}, {high:.1f}]")
            first = data[(data.arm == arm) & (data.variant == variant) & (data.timesteps == steps[0])].set_index(["robot", "seed"])
            last = data[(data.arm == arm) & (data.variant == variant) & (data.timesteps == steps[-1])].set_index(["robot", "seed"])
            change = by_run(last["return"] - first["return"])
            low, high = run_interval(change)
            baseline = data[(data.arm == arm) & (data.variant == names[0]) & (data.timesteps == steps[-1])].set_index(["robot", "seed"])
            own, other = last["return"].unstack("robot"), baseline["return"].unstack("robot")
            robots = own.columns.intersection(other.columns)
            own, other = own[robots].dropna(axis=1), other[robots].dropna(axis=1)
            robots = own.columns.intersection(other.columns)
            own, other = own[robots].to_numpy(), other[robots].to_numpy()
            paired = own.mean() - other.mean()
            # the first variant against itself is 0 by construction: its runs are not resampled against themselves
            p_low, p_high = (0.0, 0.0) if variant == names[0] else paired_run_interval(own, other)
            lines.append(
                f"| {arm} | {variant} | " + " | ".join(cells) + f" | {change.mean():+.1f} [{low:+.1f}, {high:+.1f}] "
                f"| {paired:+.1f} [{p_low:+.1f}, {p_high:+.1f}] | {explained_variance(args, variant, arm):.2f} |"
            )
    lines += [
        "",
        "Explained variance: SB3's `train/explained_variance` of the critic's values on each rollout's returns, averaged over "
        "the second half of the run's updates and the seeds (0: the values explain nothing of the returns, 1: all of them).",
    ]
    (args.out / "README.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def explained_variance(args: argparse.Namespace, variant: str, arm: str) -> float:
    """Mean ``train/explained_variance`` over the second half of each seed's updates."""
    means = []
    for seed in args.seeds:
        progress = read_progress(transfer_folder(args.out / variant, args.task, arm, seed))  # every attempt of a resumed run
        values = progress["train/explained_variance"]
        values = values[~np.isnan(values)]
        means.append(values[len(values) // 2 :].mean())
    return float(np.mean(means))


if __name__ == "__main__":
    main()
