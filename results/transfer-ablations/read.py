"""Read the ablation race by its rule (``../transfer-recipes/rule.md``, the 13:50 addendum and the terms of 16:50):
each student's last evaluation against its many-draw start, with its KL per update; ``reading.md`` (also the
table of ``README.md``) and ``ablations.png``.

    python results/transfer-ablations/read.py

Rows: the three ablated students and their comparator, the DivMorph student distilled and raced alike (400k
DAgger steps, the same terms). Intervals: 95% bootstrap over training runs (seeds) and robots for the gain (the
race's reading; its rule named robot x seed pairs, but a run's robots share its policy: the run is the unit that
varies), and for the gain against the comparator's (each student's runs resampled apart, robots paired; a check
added after the race, not part of its rule); t over seeds for the stochastic training return.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from divmorph.pipeline.figures import save_png  # noqa: E402
from divmorph.pipeline.metrics import paired_run_interval, run_interval, seed_interval  # noqa: E402

HERE = Path(__file__).resolve().parent
TASKS = {"Escape": "Escape, low start (Incline's gates)", "PointNav": "PointNav, goal bounded at 10 m (Patrol's gates)"}
STUDENTS = {
    "divmorph": "DivMorph (comparator)",
    "no-kdiv-transformer": "no diversion in the Transformer",
    "no-kdiv-decoder": "no diversion in the decoder",
    "no-orthogonality": "no orthogonality (free square factors)",
}
#: the part each ablation leaves undiverted: what it names if it learns where DivMorph does not
PARTS = {
    "no-kdiv-transformer": "the Transformer's fixed selection",
    "no-kdiv-decoder": "the decoder's fixed selection",
    "no-orthogonality": "the Cayley square factors",
}
#: MetaMorph⚗'s median approx. KL per update on Escape at its nominal rate (``../transfer-recipes/``, G's section)
DENSE_KL = 0.012
#: MetaMorph⚗'s many-draw start on Escape: a start at or above it leaves no room a student is known to climb into
ROOM = 5.2
WINDOW = 30
#: decimals the table prints returns with: Escape's are ~1, PointNav's ~200
DECIMALS = {"Escape": 2, "PointNav": 1}
MARKER = "<!-- transfer-ablations-reading -->"


def runs(task: str, student: str, here: Path = HERE) -> tuple[pd.DataFrame, pd.DataFrame, pd.Series]:
    """``(curves, training log, start per robot)`` of a student on a task; empty frames when it has no runs."""
    if not (here / "curves.csv.gz").is_file():  # nothing collected yet
        return pd.DataFrame(), pd.DataFrame(), pd.Series(dtype=float)
    curves, training = pd.read_csv(here / "curves.csv.gz"), pd.read_csv(here / "training.csv.gz")
    starts = (
        pd.read_csv(here / "starts.csv")
        if (here / "starts.csv").is_file()
        else pd.DataFrame(columns=["task", "student", "robot", "return"])
    )
    mine = starts[(starts.task == task) & (starts.student == student)]
    return (
        curves[(curves.task == task) & (curves.student == student)],
        training[(training.task == task) & (training.student == student)],
        mine.set_index("robot")["return"],
    )


def gains(curves: pd.DataFrame, start: pd.Series) -> pd.DataFrame:
    """Seeds x training robots: the last evaluation minus the robot's many-draw start (robots every seed has)."""
    train = curves[curves.split == "train"]
    last = train[train.timesteps == train.timesteps.max()].pivot_table(index="seed", columns="robot", values="return")
    return (last - start.reindex(last.columns)).dropna(axis=1)


def against_comparator(task: str, student: str, here: Path = HERE) -> str:
    """An ablated student's gain minus the DivMorph comparator's, paired by robot, with its 95% bootstrap interval
    over each one's runs and the robots: whether it learns *more* than the comparator, not only whether it learns.
    Added after the race (not part of its rule): two students whose intervals fall on either side of 0 can gain the same."""
    if student == "divmorph":
        return "(the comparator)"
    mine, theirs = runs(task, student, here), runs(task, "divmorph", here)
    if theirs[0].empty or theirs[2].empty:
        return "comparator not run"
    own, other = gains(mine[0], mine[2]), gains(theirs[0], theirs[2])
    robots = own.columns.intersection(other.columns)
    own, other = own[robots].to_numpy(), other[robots].to_numpy()
    lo, hi = paired_run_interval(own, other)
    d = DECIMALS[task]
    return f"{own.mean() - other.mean():+.{d}f} [{lo:+.{d}f}, {hi:+.{d}f}]"


def stochastic(training: pd.DataFrame) -> np.ndarray:
    """Per seed: mean stochastic training return of the last ``WINDOW`` updates minus the first ``WINDOW``."""
    out = []
    for _, run in training.sort_values("timesteps").groupby("seed"):
        returns = run.training_return.to_numpy()
        out.append(returns[-WINDOW:].mean() - returns[:WINDOW].mean())
    return np.array(out)


def by_the_rule(task: str, student: str, start: float, reading: str, kl: pd.Series) -> str:
    """The rule's verdict for a row (Escape names a part; PointNav is reported beside, deciding nothing)."""
    if task != "Escape":
        return "reported beside (PointNav decides nothing by itself)"
    if start >= ROOM:
        return f"no reading: starts at or above MetaMorph⚗'s start ({ROOM})"
    if not DENSE_KL / 2 <= kl.median() <= 2 * DENSE_KL or kl.max() > 0.1:
        return f"no reading: KL per update off MetaMorph⚗'s ({DENSE_KL})"
    if student == "divmorph":
        return "the block" if reading != "learns" else "DivMorph learns: no block to name"
    return f"names {PARTS[student]}" if reading == "learns" else "does not free it"


def row(task: str, student: str, here: Path = HERE) -> tuple[str, tuple[np.ndarray, np.ndarray], str] | None:
    """A table row, the mean curve (start at step 0) and the rule's verdict of a student on a task; ``None``
    without finished runs or a measured start."""
    curves, training, start = runs(task, student, here)
    if curves.empty or start.empty:
        return None
    gain = gains(curves, start).to_numpy()
    lo, hi = run_interval(gain)
    reading = "learns" if lo > 0 else "loses" if hi < 0 else "neither, within noise"
    train = curves[curves.split == "train"]
    robots = sorted(set(train.robot) & set(start.index))
    mean = train[train.robot.isin(robots) & (train.timesteps > 0)].groupby("timesteps")["return"].mean()
    steps = np.concatenate([[0.0], mean.index.to_numpy(float)])
    curve = np.concatenate([[start.reindex(robots).mean()], mean.to_numpy()])
    noisy = stochastic(training)
    noisy_lo, noisy_hi = seed_interval(noisy)
    held = curves[curves.split == "novel"].pivot_table(index=["seed", "robot"], columns="timesteps", values="return")
    kl = training.approx_kl
    medians = training.groupby("seed").approx_kl.median()
    verdict = by_the_rule(task, student, curve[0], reading, kl)
    d = DECIMALS[task]
    text = (
        f"| {TASKS[task]} | {STUDENTS[student]} | {curves.seed.nunique()} | {curve[0]:.{d}f} | {curve[-1]:.{d}f} "
        f"| {gain.mean():+.{d}f} [{lo:+.{d}f}, {hi:+.{d}f}] | {reading} | {against_comparator(task, student, here)} "
        f"| {noisy.mean():+.{d}f} [{noisy_lo:+.{d}f}, {noisy_hi:+.{d}f}] "
        f"| {held.iloc[:, 0].mean():.{d}f} -> {held.iloc[:, -1].mean():.{d}f} "
        f"| {kl.median():.4f} ({medians.min():.4f}-{medians.max():.4f}) / {kl.max():.3f} "
        f"| {verdict} |"
    )
    return text, (steps, curve), verdict


def conclusion(verdicts: dict[str, str]) -> str:
    """The rule's answer from the students' Escape verdicts (``{student: verdict}``, the comparator's included)."""
    missing = [STUDENTS[s] for s in STUDENTS if s not in verdicts]
    if missing:
        return f"By the rule: not yet ({', '.join(missing)}: not run)."
    if verdicts["divmorph"] != "the block":  # it learns here, or is unread: the ablations have nothing to free
        return f"By the rule: no part named; the DivMorph student itself: {verdicts['divmorph']}."
    named = [PARTS[s] for s, verdict in verdicts.items() if verdict.startswith("names")]
    unread = [STUDENTS[s] for s, verdict in verdicts.items() if s in PARTS and verdict.startswith("no reading")]
    if named:
        held = named[0] if len(named) == 1 else ", ".join(named[:-1]) + " and " + named[-1]
        if len(named) == 1:
            return f"By the rule: {held} holds the fixed-gate block."
        return f"By the rule: {held} hold the fixed-gate block together (without any one of them the student learns)."
    if unread:
        return f"By the rule: no part named; no reading for {', '.join(unread)}."
    return "By the rule: none learns -- no single diverted part holds the block (the fixed selection in both parts together, or what distillation put there)."


def figure(means: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], path: Path) -> None:
    fig, axes = plt.subplots(1, len(means), figsize=(5.4 * len(means), 3.9), squeeze=False)
    colors = dict(zip(STUDENTS, plt.get_cmap("tab10").colors))
    for ax, (task, curves) in zip(axes[0], means.items()):
        for student, (steps, curve) in curves.items():
            ax.plot(
                steps / 1e3, curve, marker="o", lw=2.2 if student == "divmorph" else 1.4, color=colors[student], label=STUDENTS[student]
            )
        ax.set_title(TASKS[task], fontsize=9)
        ax.set_xlabel("env steps on the task (thousands)")
        ax.set_ylabel("deterministic return (mean over robots, seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        "The students distilled for 400k steps, under fixed gates at the dense rate (3 seeds x 602,112 steps; step 0 = many-draw start)",
        fontsize=9,
    )
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


def main(here: Path = HERE) -> str:
    lines = [
        "| task | student | seeds | start | last | last - start [95% CI] | reading | gain - comparator's, paired by robot "
        "[95% CI] (added after the race) | stochastic training return, last - "
        "first 30 updates [95% CI] | held-out robots: step 0 -> last | approx. KL per update: median (per seed) / largest | by the rule |",
        "|---|---|---:|---:|---:|---|---|---|---|---|---|---|",
    ]
    means: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    verdicts: dict[str, str] = {}
    for task in TASKS:
        for student in STUDENTS:
            found = row(task, student, here)
            if found is None:
                lines.append(f"| {TASKS[task]} | {STUDENTS[student]} | not run | | | | | | | | | |")
                continue
            lines.append(found[0])
            means.setdefault(task, {})[student] = found[1]
            if task == "Escape":
                verdicts[student] = found[2]
    table = "\n".join(lines) + "\n\n" + conclusion(verdicts)
    (here / "reading.md").write_text(table + "\n")
    readme = here / "README.md"
    if readme.is_file() and readme.read_text().count(MARKER.replace("<!-- ", "<!-- /")) == 1:
        text = readme.read_text()
        head, rest = text.split(MARKER + "\n", 1)
        _, tail = rest.split(MARKER.replace("<!-- ", "<!-- /"), 1)
        readme.write_text(f"{head}{MARKER}\n{table}\n{MARKER.replace('<!-- ', '<!-- /')}{tail}")
    if means:
        figure(means, here / "ablations.png")
    print(table)
    return table


if __name__ == "__main__":
    main()
