"""Where does scratch get with 4x the race's budget? A control for a transfer race's speed-ups.

    python results/cpu100-scratch-long/scratch_control.py --race results/cpu100 --control results/cpu100-scratch-long

In a race where scratch learns little within the budget, the speed-up of an arm over scratch is only a
lower bound (``>= budget / the arm's steps``). The control trains scratch (MetaMorph from random
weights) longer on the same tasks, robots and evaluation (``transfer.eval_robots``, deterministic
episodes) and measures, against the level the race fixed for each task and split
(:func:`divmorph.pipeline.metrics.level_for`; it is not recomputed with the control in it), the
steps scratch needs to hold it: each arm's speed-up is then the control's steps / the arm's steps
(from the race's ``transfer/<task>/metrics.csv``), still a lower bound where the control never holds
the level. It also gives, for each arm, the steps from which the control holds that arm's final
return: what the arm's budget is worth in scratch's steps. Intervals resample robots (the control
has one seed). Writes ``control.csv``,
``control.md`` and ``control.png`` into the control's folder.
"""

from __future__ import annotations

import argparse
import csv
import math
import platform
import time
from pathlib import Path

import numpy as np

from divmorph.pipeline.curves import seed_robot_curves
from divmorph.pipeline.metrics import bootstrap_curves, interval, stack_seeds, steps_to_hold
from divmorph.pipeline.metrics import speedup as metrics_speedup
from divmorph.pipeline.figures import save_png
from divmorph.pipeline.files import read_csv_rows

SPLITS = ("train", "novel")
#: the race's arms drawn beside the control (every arm of the race)
ARMS = ("divmorph", "scratch", "closest", "distilled", "modumorph", "grl")
LABELS = {
    "divmorph": "DivMorph",
    "scratch": "MetaMorph scratch (race)",
    "closest": "MetaMorph→ (closest teacher)",
    "distilled": "MetaMorph⚗",
    "modumorph": "ModuMorph",
    "grl": "GRL",
}


def control_rows(race: Path, control: Path, task: str, split: str) -> list[dict]:
    """The control's curve summary and each race arm's speed-up over it on one task and split."""
    race_metrics = [row for row in read_csv_rows(race / "transfer" / task / "metrics.csv") if row["split"] == split]
    if not race_metrics or not race_metrics[0]["level"]:
        return []  # no level: no arm gained over the start, so no steps to count
    level = float(race_metrics[0]["level"])
    steps, values = stack_seeds(list(seed_robot_curves(control, task, "scratch", split, finished_only=True).values()))
    point = values.mean((0, 1))
    boot = bootstrap_curves(values)
    held = steps_to_hold(steps, point, level)
    boot_steps = np.array([math.inf if (x := steps_to_hold(steps, c, level)) is None else x for c in boot])
    at = {int(s): (float(point[i]), *interval(boot[:, i])) for i, s in enumerate(steps)}
    # the control where the race stopped (linear between its evaluations, as the metrics read curves)
    race_budget = int(race_metrics[0]["budget"])
    at_race_budget = (float(np.interp(race_budget, steps, point)), *interval(np.array([np.interp(race_budget, steps, c) for c in boot])))
    budget = int(steps[-1])
    rows = []
    for metric in race_metrics:
        arm_steps = float(metric["steps_to_level"]) if metric["steps_to_level"] else None
        speedup, bound = metrics_speedup(held, arm_steps, budget)  # the race's own rule, the control as scratch
        rows.append(
            {
                "task": task,
                "split": split,
                "arm": metric["arm"],
                "level": level,
                "arm_final": float(metric["final"]),
                "arm_steps_to_level": arm_steps,
                "control_budget": budget,
                "control_steps_to_level": held,
                "control_steps_lo": interval(boot_steps)[0],
                "control_steps_hi": interval(boot_steps)[1],
                "control_held": float(np.isfinite(boot_steps).mean()),
                "control_at_race_budget": at_race_budget,
                "control_final": at[budget],
                "speedup_vs_control": speedup,
                "speedup_is_lower_bound": bound,
                # what the arm's budget is worth in scratch's steps: where the control holds the arm's final return
                "control_steps_to_arm_final": steps_to_hold(steps, point, float(metric["final"])),
            }
        )
    return rows


def plot(race: Path, control: Path, tasks: list[str], target: Path) -> None:
    """Each task's race arms (mean over seeds and robots) and the control on the training robots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for arm in ARMS:
            curves = list(seed_robot_curves(race, task, arm, "train", finished_only=True).values())
            if curves:
                steps, values = stack_seeds(curves)
                ax.plot(steps / 1e6, values.mean((0, 1)), label=f"{LABELS[arm]} ({len(curves)} seed{'s' if len(curves) > 1 else ''})")
        steps, values = stack_seeds(list(seed_robot_curves(control, task, "scratch", "train", finished_only=True).values()))
        lo, hi = np.array([interval(c) for c in bootstrap_curves(values).T]).T
        ax.plot(steps / 1e6, values.mean((0, 1)), "k--", label="scratch, 4x budget (control, seed 0)")
        ax.fill_between(steps / 1e6, lo, hi, color="k", alpha=0.1)
        level = [row for row in read_csv_rows(race / "transfer" / task / "metrics.csv") if row["split"] == "train"]
        if level and level[0]["level"]:
            ax.axhline(float(level[0]["level"]), color="grey", lw=0.8, ls=":", label="the race's level")
        ax.set(title=f"{task}, training robots", xlabel="env steps (millions)", ylabel="mean return (deterministic episodes)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    save_png(fig, target)  # a 256-colour palette: a third of the RGBA file in the tracked tree


def _fmt_steps(x: float | None) -> str:
    return "never" if x is None or math.isinf(x) else f"{x / 1000:.0f}k"


def _fmt_speedup(row: dict) -> str:
    if row["speedup_vs_control"] is None:
        return "-"
    if math.isinf(row["speedup_vs_control"]):
        return "from the start"
    return f"{'>= ' if row['speedup_is_lower_bound'] else ''}{row['speedup_vs_control']:.1f}x"


def markdown(rows: list[dict], command: str, seconds: float) -> str:
    lines = [
        "# The scratch control: scratch for 4x the race's budget",
        "",
        f"`{command}` ({seconds:.0f} s on {platform.machine()}, {platform.system()}); intervals: 95% bootstrap over robots (one seed).",
        "",
        "| task | split | level (the race's) | control at the race's budget | control at its end | control holds the level from [CI] |",
        "|---|---|---:|---|---|---|",
    ]
    seen = set()
    for row in rows:
        if (row["task"], row["split"]) in seen:
            continue
        seen.add((row["task"], row["split"]))
        mid, end = row["control_at_race_budget"], row["control_final"]
        lines.append(
            f"| {row['task']} | {row['split']} | {row['level']:.1f} | {mid[0]:.1f} [{mid[1]:.1f}, {mid[2]:.1f}] | "
            f"{end[0]:.1f} [{end[1]:.1f}, {end[2]:.1f}] at {row['control_budget'] / 1e6:.1f}M | "
            f"{_fmt_steps(row['control_steps_to_level'])} [{_fmt_steps(row['control_steps_lo'])}, {_fmt_steps(row['control_steps_hi'])}] "
            f"({row['control_held']:.0%} of draws hold it) |"
        )
    lines += [
        "",
        "| task | split | arm | arm's final (race) | arm holds the level from | speed-up over the control | the control holds the arm's final from |",
        "|---|---|---|---:|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['task']} | {row['split']} | {LABELS.get(row['arm'], row['arm'])} | {row['arm_final']:.1f} | "
            f"{_fmt_steps(row['arm_steps_to_level'])} | {_fmt_speedup(row)} | {_fmt_steps(row['control_steps_to_arm_final'])} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--race", type=Path, required=True, help="the race's run folder (its transfer/<task>/metrics.csv)")
    parser.add_argument("--control", type=Path, required=True, help="the control's run folder (scratch, transfer/<task>/scratch/seed-0)")
    args = parser.parse_args()
    start = time.time()
    tasks = sorted(
        p.parent.name
        for p in args.control.glob("transfer/*/scratch")
        if seed_robot_curves(args.control, p.parent.name, "scratch", "train", True)
    )
    if not tasks:
        raise SystemExit(f"no finished scratch run in {args.control}/transfer/<task>/scratch/")
    rows = [row for task in tasks for split in SPLITS for row in control_rows(args.race, args.control, task, split)]
    with open(args.control / "control.csv", "w", newline="") as f:
        flat = [{k: (";".join(f"{x:.3f}" for x in v) if isinstance(v, tuple) else v) for k, v in row.items()} for row in rows]
        writer = csv.DictWriter(f, fieldnames=list(flat[0]))
        writer.writeheader()
        writer.writerows(flat)
    plot(args.race, args.control, tasks, args.control / "control.png")
    command = f"python results/cpu100-scratch-long/scratch_control.py --race {args.race} --control {args.control}"
    (args.control / "control.md").write_text(markdown(rows, command, time.time() - start))
    print((args.control / "control.md").read_text())


if __name__ == "__main__":
    main()
