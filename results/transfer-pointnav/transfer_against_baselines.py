"""Transfer curves read against each starting model's multi-draw zero-shot baseline (issue 42).

A transfer curve's points are deterministic evaluations, and on tasks with random goals or terrain a
point is one draw of heavy-tailed episodes: PointNav's mean over 20 robots x 3 episodes moves
between 30 and 104 for one unchanged policy (``results/novel-task-gates``). So the change from step
0 compares a fresh draw with a fixed one. This reads finished runs of ``results/finetune-known-task/finetune_known_task.py``
(``<out>/transfer/<task>/<arm>/seed-<s>/eval.csv``) and reports, per variant: the mean return at each
evaluation, the change from step 0, and the change of the last evaluation against the starting
model's mean over many draws (per robot, paired with each run), taken from
``results/novel-task-gates/novel_task_gates.py``'s rows (``--baseline-rows``).

    python results/transfer-pointnav/transfer_against_baselines.py --task PointNav --baseline-rows results/novel-task-gates/returns.csv.gz \\
        --variant "DivMorph, own gates=/work/race/gates-instruction:divmorph:divmorph:PointNav" \\
        --variant "DivMorph, Patrol's gates=/work/race/gates-closest:divmorph:divmorph:Patrol" \\
        --variant "MetaMorph->=/work/race/closest:closest:teacher-Patrol:PointNav"

A variant is ``label=folder:arm:baseline model:baseline instruction``; ``-`` for the model (scratch: no
starting model to draw from) reads it against its own step-0 points instead.

``--reference LABEL`` adds the two readings of the paper's claim (``results/transfer-pointnav/race-600k-rule.md``):
against direct fine-tuning (the abstract's 3x), the steps each variant needs to reach and hold the
reference's final return (the many-draw baseline standing for step 0; the race's own
:func:`~divmorph.pipeline.metrics.steps_to_hold`) and the gap between their last evaluations;
with ``--scratch FOLDER`` (a scratch control run, e.g. ``results/cpu100-scratch-long``) also the steps
to reach and hold scratch's final return (the paper's Sec. 6.1 wording). With the DivMorph arm as the
reference and the ablated students as the other variants, the same table is the rule's reading 4 (the
paper's ablations: the gap at the end, beside the gap the starts already had).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from divmorph.pipeline.files import is_done, log_file
from divmorph.pipeline.metrics import paired_run_interval, robot_interval, run_interval, steps_to_hold


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


def own_start(frame: pd.DataFrame) -> pd.DataFrame:
    """A variant's own step-0 points as its baseline rows (one row per robot and run: ``eval_seed`` is
    the run, ``episode`` -1 marks the rows as step-0 points, not draws of a starting model)."""
    if frame.empty:
        return pd.DataFrame(columns=["robot", "return", "eval_seed", "episode"])
    start = frame[frame.columns[0]].rename("return").reset_index()
    return start.rename(columns={"seed": "eval_seed"}).assign(episode=-1)


def last_per_run(frame: pd.DataFrame) -> pd.Series:
    """Each (robot, seed)'s return at its run's own last evaluation (a resumed run ends a few steps off the others')."""
    return frame.apply(lambda row: row.dropna().iloc[-1], axis=1)


def last_per_robot(frame: pd.DataFrame) -> pd.Series:
    """Each robot's return at its runs' own last evaluations, averaged over the runs (seeds)."""
    return last_per_run(frame).groupby(level="robot").mean()


def by_run(values: pd.Series) -> pd.DataFrame:
    """Seeds x robots (robots every seed has) from values indexed by (robot, seed): intervals resample the training
    runs and the robots within them, not robot x seed pairs (a run's robots share its policy)."""
    return values.unstack("robot").dropna(axis=1)


def paired(values: pd.DataFrame, comparator: pd.DataFrame) -> tuple[float, float, float]:
    """``(mean difference, low, high)`` of two (seeds, robots) tables on their common robots, paired by robot."""
    robots = values.columns.intersection(comparator.columns)
    values, comparator = values[robots].to_numpy(), comparator[robots].to_numpy()
    return (values.mean() - comparator.mean(), *paired_run_interval(values, comparator))


def start_and_curve(frame: pd.DataFrame, baseline: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """The mean curve with the many-draw baseline standing for step 0: the evaluations every run made,
    then each run's own last evaluation at the last step (a resumed run ends a few steps off the others')."""
    robots = frame.index.get_level_values("robot")
    steps, values = [0.0], [float(baseline.reindex(robots).mean())]
    inner = [s for s in frame.columns if 0 < s < frame.columns.max() and frame[s].notna().all()]
    steps += [float(s) for s in inner]
    values += [float(frame[s].mean()) for s in inner]
    steps.append(float(frame.columns.max()))
    values.append(float(last_per_run(frame).mean()))
    return np.array(steps), np.array(values)


def efficiency_reading(steps_arm: float | None, steps_reference: float) -> str:
    """The rule's wording for the abstract's 3x (``race-600k-rule.md``); ``steps_reference`` is always
    found, the level being the reference's own final return."""
    if steps_arm is None:
        return "does not hold at this budget (never reaches and holds the level)"
    if steps_arm == 0 and steps_reference == 0:
        return "level from the start; no efficiency difference"
    if steps_arm == 0 or steps_arm <= steps_reference / 3:
        ratio = "from the start" if steps_arm == 0 else f"{steps_reference / steps_arm:.1f}x"
        return f"holds ({ratio})"
    if steps_reference == 0:
        return "does not hold (direct fine-tuning holds the level from the start)"
    return f"does not hold ({steps_reference / steps_arm:.2f}x)"


def readings(variants: list, task: str, reference: str, scratch: Path | None) -> list[str]:
    """Both readings of the paper's claim, one line per variant (see the module docstring)."""
    found = {label: (start, frame) for label, start, frame in variants if not frame.empty}
    if reference not in found:
        return [f"(no finished run of the reference {reference!r})"]
    curve = {label: start_and_curve(frame, start.groupby("robot")["return"].mean()) for label, (start, frame) in found.items()}
    level = curve[reference][1][-1]
    to_level = {label: steps_to_hold(*curve[label], level) for label in found}
    ref_start = found[reference][0].groupby("robot")["return"].mean()
    digits = 1 if abs(level) < 50 else 0
    lines = [
        "",
        f"Against the reference, {reference} (its final return, {level:.{digits}f}: the steps to reach and hold it; "
        "the reading is the abstract's 3x when the reference is direct fine-tuning):",
        "",
        "| variant | steps to the level | reading | many-draw start minus the reference's, per robot [95% CI] "
        "| last minus the reference's last, per robot [95% CI] | gain minus the reference's gain, per robot [95% CI] |",
        "|---|---:|---|---|---|---|",
    ]
    for label in found:
        steps = to_level[label]
        mine, theirs = by_run(last_per_run(found[label][1])), by_run(last_per_run(found[reference][1]))
        gap_mean, low, high = paired(mine, theirs)
        # a gap at the end that was there before any fine-tuning is the starts' (many draws of fixed models: robots only)
        start_gap = (found[label][0].groupby("robot")["return"].mean() - ref_start).dropna()
        s_low, s_high = robot_interval(start_gap.to_numpy()) if len(start_gap) else (np.nan, np.nan)
        # what fine-tuning added, each from its own many-draw start: the comparison of two arms' learning
        own_start = found[label][0].groupby("robot")["return"].mean()
        gain_mean, g_low, g_high = paired(mine - own_start.reindex(mine.columns), theirs - ref_start.reindex(theirs.columns))
        reference_steps = to_level[reference]
        assert reference_steps is not None  # the reference's last point is its own final return
        reading = "(the reference)" if label == reference else efficiency_reading(steps, reference_steps)
        told = "not reached" if steps is None else f"{steps / 1000:.0f}k"
        lines.append(
            f"| {label} | {told} | {reading} | {start_gap.mean():+.{digits}f} [{s_low:+.{digits}f}, {s_high:+.{digits}f}] "
            f"| {gap_mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}] "
            f"| {gain_mean:+.{digits}f} [{g_low:+.{digits}f}, {g_high:+.{digits}f}] |"
        )
    if scratch is not None:
        control = curves(scratch, task, "scratch")
        if control.empty:
            return lines + ["", f"(no finished scratch run of {task} in {scratch})"]
        final = float(last_per_robot(control).mean())
        lines += ["", f"Against scratch (its final return after {int(control.columns.max()) / 1e6:.1f}M steps, {final:.{digits}f}):", ""]
        for label in found:
            steps = steps_to_hold(*curve[label], final)
            told = "never holds it" if steps is None else ("from the start" if steps == 0 else f"after {steps / 1000:.0f}k steps")
            lines.append(f"- {label}: {told}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--baseline-rows", type=Path, required=True)
    parser.add_argument("--variant", action="append", required=True, metavar="LABEL=FOLDER:ARM:MODEL:INSTRUCTION")
    parser.add_argument("--reference", metavar="LABEL", help="the direct fine-tuning variant whose final return sets the level")
    parser.add_argument("--scratch", type=Path, help="a scratch control run folder (its transfer/<task>/scratch/seed-*)")
    args = parser.parse_args()
    rows = pd.read_csv(args.baseline_rows)
    rows = rows[rows.task == args.task]
    lines = []
    variants = []
    for item in args.variant:
        label, _, spec = item.partition("=")
        folder, arm, model, told = spec.split(":")
        frame = curves(Path(folder), args.task, arm)
        # the starting model's many-draw rows (evaluation seeds x episodes per robot) beside the run's curves
        base = own_start(frame) if model == "-" else rows[(rows.model == model) & (rows.instruction_of == told)]
        variants.append((label, base, frame))
    # the evaluation steps of every variant (a run resumed from a checkpoint ends a few steps off the others')
    header = sorted({step for *_, frame in variants for step in frame.columns})
    for label, base, frame in variants:
        if frame.empty:
            lines.append(f"| {label} | 0 | (no finished run) |")
            continue
        per_robot = base.groupby("robot")["return"].mean()
        steps = list(frame.columns)
        digits = 1 if abs(per_robot.mean()) < 50 else 0  # Escape's returns are a few units
        means = " | ".join(f"{frame[s].mean():.{digits}f}" if s in frame else "-" for s in header)
        last = last_per_run(frame)
        from_zero = by_run(last - frame[steps[0]]).to_numpy()
        against = by_run(last - per_robot.reindex(frame.index.get_level_values("robot")).to_numpy()).to_numpy()
        z_low, z_high = run_interval(from_zero)
        a_low, a_high = run_interval(against)
        runs = frame.index.get_level_values("seed").nunique()
        draws = (
            "its step 0"
            if len(base) and (base.episode == -1).all()
            else f"{base.eval_seed.nunique()} seeds x {base.episode.nunique()} episodes"
        )
        lines.append(
            f"| {label} | {runs} | {per_robot.mean():.{digits}f} ({draws}) | {means} "
            f"| {from_zero.mean():+.{digits}f} [{z_low:+.{digits}f}, {z_high:+.{digits}f}] "
            f"| **{against.mean():+.{digits}f} [{a_low:+.{digits}f}, {a_high:+.{digits}f}]** |"
        )
    steps_header = " | ".join(f"{int(s) / 1000:g}k" for s in header)
    print(
        f"| variant | runs | zero-shot baseline (many draws) | {steps_header} | change from step 0 [95% CI] | last against the baseline [95% CI] |"
    )
    print("|---|---:|---:|" + "---:|" * len(header) + "---|---|")
    print("\n".join(lines))
    if args.reference:
        print("\n".join(readings(variants, args.task, args.reference, args.scratch)))


if __name__ == "__main__":
    np.set_printoptions(precision=2)
    main()
