"""Transfer curves read against each starting model's multi-draw zero-shot baseline (issue 42).

A transfer curve's points are deterministic evaluations, and on tasks with random goals or terrain a
point is one draw of heavy-tailed episodes: PointNav's mean over 20 robots x 3 episodes moves
between 30 and 104 for one unchanged policy (``results/novel-task-gates``). So the change from step
0 compares a fresh draw with a fixed one. This reads finished runs of ``studies/finetune_known_task.py``
(``<out>/transfer/<task>/<arm>/seed-<s>/eval.csv``) and reports, per variant: the mean return at each
evaluation, the change from step 0, and the change of the last evaluation against the starting
model's mean over many draws (per robot, paired with each run), taken from
``studies/novel_task_gates.py``'s rows (``--baseline-rows``).

    python studies/transfer_against_baselines.py --task PointNav --baseline-rows results/novel-task-gates/returns.csv.gz \\
        --variant "DivMorph, own gates=/work/race/gates-instruction:divmorph:divmorph:PointNav" \\
        --variant "DivMorph, Patrol's gates=/work/race/gates-closest:divmorph:divmorph:Patrol" \\
        --variant "MetaMorph->=/work/race/closest:closest:teacher-Patrol:PointNav"

A variant is ``label=folder:arm:baseline model:baseline instruction``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from sb3_divmorph.pipeline.files import is_done, log_file
from sb3_divmorph.pipeline.metrics import robot_interval


def curves(folder: Path, task: str, arm: str) -> pd.DataFrame:
    """(robot, seed) x timesteps: mean return over a point's episodes, training split, finished runs."""
    parts = []
    for run in sorted((folder / "transfer" / task / arm).glob("seed-*")):
        if not is_done(run):
            continue
        frame = pd.read_csv(log_file(run / "eval.csv"))
        frame = frame[frame.split == "train"].groupby(["timesteps", "robot"])["return"].mean().unstack("timesteps")
        frame.index = pd.MultiIndex.from_product([frame.index, [run.name]], names=["robot", "seed"])
        parts.append(frame)
    return pd.concat(parts) if parts else pd.DataFrame()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--baseline-rows", type=Path, required=True)
    parser.add_argument("--variant", action="append", required=True, metavar="LABEL=FOLDER:ARM:MODEL:INSTRUCTION")
    args = parser.parse_args()
    rows = pd.read_csv(args.baseline_rows)
    rows = rows[rows.task == args.task]
    lines = []
    variants = []
    for item in args.variant:
        label, _, spec = item.partition("=")
        folder, arm, model, told = spec.split(":")
        variants.append((label, model, told, curves(Path(folder), args.task, arm)))
    # the evaluation steps of every variant (a run resumed from a checkpoint ends a few steps off the others')
    header = sorted({step for *_, frame in variants for step in frame.columns})
    for label, model, told, frame in variants:
        if frame.empty:
            lines.append(f"| {label} | 0 | (no finished run) |")
            continue
        base = rows[(rows.model == model) & (rows.instruction_of == told)]
        per_robot = base.groupby("robot")["return"].mean()
        steps = list(frame.columns)
        digits = 1 if abs(per_robot.mean()) < 50 else 0  # Escape's returns are a few units
        means = " | ".join(f"{frame[s].mean():.{digits}f}" if s in frame else "-" for s in header)
        # each run's own last evaluation
        last = frame.apply(lambda row: row.dropna().iloc[-1], axis=1)
        from_zero = (last - frame[steps[0]]).to_numpy()
        against = (last - per_robot.reindex(frame.index.get_level_values("robot")).to_numpy()).to_numpy()
        z_low, z_high = robot_interval(from_zero)
        a_low, a_high = robot_interval(against)
        runs = frame.index.get_level_values("seed").nunique()
        lines.append(
            f"| {label} | {runs} | {per_robot.mean():.{digits}f} ({base.eval_seed.nunique()} seeds x {base.episode.nunique()} episodes) | {means} "
            f"| {from_zero.mean():+.{digits}f} [{z_low:+.{digits}f}, {z_high:+.{digits}f}] "
            f"| **{against.mean():+.{digits}f} [{a_low:+.{digits}f}, {a_high:+.{digits}f}]** |"
        )
    steps_header = " | ".join(f"{int(s) / 1000:g}k" for s in header)
    print(
        f"| variant | runs | zero-shot baseline (many draws) | {steps_header} | change from step 0 [95% CI] | last against the baseline [95% CI] |"
    )
    print("|---|---:|---:|" + "---:|" * len(header) + "---|---|")
    print("\n".join(lines))


if __name__ == "__main__":
    np.set_printoptions(precision=2)
    main()
