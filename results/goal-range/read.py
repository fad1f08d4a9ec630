"""Read the goal-in-range control (``rule.md``): each arm's last evaluation against its many-draw start,
with the goal bounded at 10 m and, beside it, the race's runs with the raw goal; the table and figure of ``README.md``.

    python results/goal-range/read.py

Bounded: ``curves.csv.gz`` and ``starts.csv`` (``collect.py`` gathers them from the runs). Raw:
``../transfer-pointnav/runs-600k/`` and the starts in ``../novel-task-gates/returns.csv.gz`` (the same
robots, evaluation seeds and episodes).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from divmorph.pipeline.figures import save_png  # noqa: E402
from divmorph.pipeline.metrics import paired_run_interval, robot_interval, run_interval  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent
#: arm -> (label, raw race folder, what it is told in the raw starts' rows, the starts' model label)
ARMS = {
    "divmorph": ("DivMorph arm (fixed gates, Patrol's)", "PointNav-gates-closest", "Patrol", "divmorph"),
    "distilled": ("MetaMorph⚗ (fine-tuned)", "PointNav-distilled", "PointNav", "distilled"),
    "closest": ("MetaMorph→ (Patrol's teacher, fine-tuned)", "PointNav-closest", "PointNav", "teacher-Patrol"),
}


def numbered(frame: pd.DataFrame) -> pd.DataFrame:
    """One run's training-robot curve with its evaluations numbered, the last one last. The raw race's runs
    evaluated at 600,000 and again at their last step: a point within 10k steps before the last is that point."""
    steps = sorted(frame.timesteps.unique())
    steps = [t for t in steps if t == steps[-1] or steps[-1] - t > 10_000]
    frame = frame[frame.timesteps.isin(steps)]
    return frame.assign(point=frame.timesteps.map({t: i for i, t in enumerate(steps)}))


def raw_curves(folder: Path, arm: str) -> pd.DataFrame:
    """Per (seed, point, robot): the mean deterministic return on the training curve robots, raw goal."""
    parts = []
    for path in sorted((folder / "transfer" / "PointNav" / arm).glob("seed-*/eval.csv.gz")):
        frame = pd.read_csv(path)
        frame = frame[frame.split == "train"].groupby(["timesteps", "robot"], as_index=False)["return"].mean()
        parts.append(numbered(frame).assign(seed=int(path.parent.name.split("-")[1])))
    return pd.concat(parts) if parts else pd.DataFrame(columns=["timesteps", "point", "robot", "return", "seed"])


def bounded_curves(arm: str) -> pd.DataFrame:
    """The same with the goal bounded (``curves.csv.gz``); only an arm whose three seeds finished."""
    table = pd.read_csv(HERE / "curves.csv.gz")
    table = table[(table.arm == arm) & (table.split == "train")]
    if table.seed.nunique() < 3:
        return pd.DataFrame(columns=["timesteps", "point", "robot", "return", "seed"])
    return pd.concat(numbered(run).assign(seed=seed) for seed, run in table.groupby("seed"))


def raw_starts(told: str, model: str) -> pd.Series:
    rows = pd.read_csv(RESULTS / "novel-task-gates" / "returns.csv.gz")
    rows = rows[(rows.task == "PointNav") & (rows.model == model) & (rows.instruction_of == told)]
    return rows.groupby("robot")["return"].mean()


def bounded_starts(arm: str) -> pd.Series | None:
    starts = pd.read_csv(HERE / "starts.csv", index_col="robot")
    return starts[arm] if arm in starts else None


def gain(curve: pd.DataFrame, start: pd.Series) -> pd.Series:
    """Per (robot, seed): each run's last evaluation minus the robot's many-draw start."""
    last = curve[curve.point == curve.point.max()].set_index(["robot", "seed"])["return"]
    return (last - start.reindex(last.index.get_level_values(0)).to_numpy()).dropna()


def by_run(change: pd.Series) -> pd.DataFrame:
    """Seeds x robots (robots every seed has): the unit an interval resamples is the training run, and robots within it."""
    return change.unstack("robot").dropna(axis=1)


def cell(values: np.ndarray, digits: int = 0) -> str:
    """Mean [95% CI]: over training runs and robots for a (seeds, robots) array, over robots for per-robot values."""
    lo, hi = run_interval(values) if values.ndim == 2 else robot_interval(values)
    return f"{values.mean():+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"


def paired_cell(values: pd.DataFrame, comparator: pd.DataFrame) -> str:
    """Mean difference [95% CI] of two arms' (seeds, robots) gains, paired by robot, each arm's runs resampled apart."""
    robots = values.columns.intersection(comparator.columns)
    values, comparator = values[robots].to_numpy(), comparator[robots].to_numpy()
    lo, hi = paired_run_interval(values, comparator)
    return f"{values.mean() - comparator.mean():+.0f} [{lo:+.0f}, {hi:+.0f}]"


def main() -> None:
    lines = [
        "| arm (PointNav, 3 seeds x 602,112 steps) | goal input | many-draw start | last evaluation | last against the start [95% CI] | reading |",
        "|---|---|---:|---:|---|---|",
    ]
    figure, axes = plt.subplots(1, len(ARMS), figsize=(4.2 * len(ARMS), 3.6), sharey=True)
    per_robot_gain = {}
    for ax, (arm, (label, raw_folder, told, model)) in zip(axes, ARMS.items(), strict=True):
        for goal, curve, start in (
            ("raw", raw_curves(RESULTS / "transfer-pointnav" / "runs-600k" / raw_folder, arm), raw_starts(told, model)),
            ("goal_range 10", bounded_curves(arm), bounded_starts(arm)),
        ):
            if curve.empty or start is None:
                lines.append(f"| {label} | {goal} | – | – | not run | – |")
                continue
            change = by_run(gain(curve, start))
            per_robot_gain[(arm, goal)] = change
            lo, hi = run_interval(change.to_numpy())
            reading = "learns" if lo > 0 else "loses" if hi < 0 else "neither, within noise"
            last = curve[curve.point == curve.point.max()]["return"].mean()
            lines.append(f"| {label} | {goal} | {start.mean():.0f} | {last:.0f} | {cell(change.to_numpy())} | {reading} |")
            mean = curve.groupby("point").agg(steps=("timesteps", "mean"), value=("return", "mean"))
            steps = np.r_[0, mean.steps.to_numpy()[1:]] / 1e3
            values = np.r_[start.mean(), mean.value.to_numpy()[1:]]
            ax.plot(steps, values, marker="o", label=f"{goal} (start: mean of 15 episodes per robot)")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("PPO env steps (thousands)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("deterministic return, 20 training robots\n(mean of 3 seeds x 5 episodes)")
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=2, fontsize=8)
    figure.suptitle("PointNav fine-tuning with raw and bounded (10 m) goal input", fontsize=10)
    figure.tight_layout(rect=(0, 0.08, 1, 1))
    save_png(figure, HERE / "pointnav.png")
    extra = []
    for arm in ARMS:
        if (arm, "raw") in per_robot_gain and (arm, "goal_range 10") in per_robot_gain:
            diff = paired_cell(per_robot_gain[(arm, "goal_range 10")], per_robot_gain[(arm, "raw")])
            extra.append(f"- {ARMS[arm][0]}: gain with the bounded goal minus gain with the raw one, per robot: {diff}")
    if ("divmorph", "goal_range 10") in per_robot_gain and ("distilled", "goal_range 10") in per_robot_gain:
        diff = paired_cell(per_robot_gain[("divmorph", "goal_range 10")], per_robot_gain[("distilled", "goal_range 10")])
        extra.append(f"- bounded goal: the DivMorph arm's gain minus MetaMorph⚗'s, per robot: {diff}")
    starts = []
    for arm, (label, _, told, model) in ARMS.items():
        bounded = bounded_starts(arm)
        if bounded is not None:
            diff = (bounded - raw_starts(told, model).reindex(bounded.index)).dropna().to_numpy()
            starts.append(f"- {label}: many-draw start with the bounded goal minus with the raw one, per robot: {cell(diff)}")
    text = "\n".join(lines + ["", *extra, *starts])
    (HERE / "reading.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
