"""The candidate recipe's confirmation on the novel tasks it was not chosen on (``rule.md``'s addendum):
fixed gates at a KL of 0.01 per update (K) against the race's arms on Escape and Exploration, with both
readings of the paper's 3x claim and the stochastic training return beside the deterministic evaluation;
and, on Escape, the controls F (every DivMorph weight at MetaMorph⚗'s rate, rotations frozen: the 08:30
addendum), G (F with the gates fixed: the 09:45 addendum) and L (the fixed-gate arm from a low start,
told Incline's instruction: the 11:00 addendum; G-L, G from there: the 12:00 one); ``confirm.md`` and ``confirm.png``.

    python results/transfer-recipes/confirm.py

Curves: K's, F's and G's from ``curves.csv.gz`` / ``training.csv.gz`` (``collect.py``); the race's from
``../transfer-pointnav/runs-600k/`` (same terms, robots, episodes and budget, nominal rates). A fine-tuned
arm's step 0 is its many-draw start (``../novel-task-gates/returns.csv.gz``: 5 evaluation seeds x 3 episodes
per robot), scratch's its own step 0. Intervals: 95% bootstrap over robots and seeds (robots paired across
arms) for the readings of 3x, over training runs (seeds) and robots for the gains (a run's robots share its
policy: not independent draws); the stochastic training return's over the seeds (t). Held-out robots: the 20 curve robots of the official test split,
against each run's own step-0 evaluation (a single draw).

The two readings of "~3x more sample-efficient":
- against scratch: the steps from which an arm's mean curve holds scratch's final return (linear between
  evaluations, to the end), as a multiple of scratch's own (its 602,112);
- against direct fine-tuning: the same with MetaMorph→'s final return as the level and MetaMorph→'s own steps
  to hold it as the reference. "from the start": held from step 0 (a head start, not faster adaptation).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from divmorph.pipeline.figures import save_png  # noqa: E402
from divmorph.pipeline.metrics import run_interval, seed_interval, steps_to_hold  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent
RACE = RESULTS / "transfer-pointnav" / "runs-600k"
TASKS = {"Escape": "FT", "Exploration": "Obstacle"}  # novel task -> the training task closest by instruction
ARMS = ("K", "F", "G", "divmorph", "closest", "distilled", "scratch", "L", "GL")
#: this study's arms (``curves.csv.gz`` variants ``<arm>-<task>``); each starts as the fixed-gate arm, but L and
#: GL, which are told Incline's instruction (their router selects Incline's tailors: a low start)
OURS = ("K", "F", "G", "L", "GL")
LABELS = {
    "K": "fixed gates, KL 0.01 per update (candidate)",
    "F": "every DivMorph weight, rotations frozen (F, control)",
    "G": "fixed gates, every active weight 1x, rotations frozen (G, control)",
    "L": "fixed gates, Incline's tailors: a low start (L, control)",
    "GL": "L with every active weight 1x, rotations frozen (G-L, control)",
    "divmorph": "fixed gates, nominal rate",
    "closest": "MetaMorph→ (direct fine-tuning)",
    "distilled": "MetaMorph⚗ (dense distilled student)",
    "scratch": "MetaMorph from scratch",
}
#: one colour per arm in every panel (a task without one of this study's arms keeps the others' colours)
COLORS = dict(zip(ARMS, plt.get_cmap("tab10").colors))
DRAWS, WINDOW = 2000, 30


def race_folder(task: str, arm: str) -> Path:
    name = {"divmorph": f"{task}-gates-closest", "closest": f"{task}-closest", "distilled": f"{task}-distilled", "scratch": "scratch"}[arm]
    return RACE / name / "transfer" / task / arm


def curves(task: str, arm: str, split: str = "train") -> pd.DataFrame:
    """Per (seed, timesteps, robot): mean deterministic return on the curve robots of ``split``."""
    if arm in OURS:
        table = pd.read_csv(HERE / "curves.csv.gz")
        return table[(table.variant == f"{arm}-{task}") & (table.split == split)][["seed", "timesteps", "robot", "return"]]
    parts = []
    for path in sorted(race_folder(task, arm).glob("seed-*/eval.csv.gz")):
        frame = pd.read_csv(path)
        frame = frame[frame.split == split].groupby(["timesteps", "robot"], as_index=False)["return"].mean()
        parts.append(frame.assign(seed=int(path.parent.name.split("-")[1])))
    return pd.concat(parts)[["seed", "timesteps", "robot", "return"]]


def start(task: str, arm: str) -> pd.Series | None:
    """The many-draw start per robot of a fine-tuned arm (``None``: scratch, its own step 0)."""
    if arm == "scratch":
        return None
    told_by = {arm: ("divmorph", TASKS[task]) for arm in (*OURS, "divmorph")} | {low: ("divmorph", "Incline") for low in ("L", "GL")}
    model, told = told_by.get(arm, (f"teacher-{TASKS[task]}" if arm == "closest" else arm, task))
    rows = pd.read_csv(RESULTS / "novel-task-gates" / "returns.csv.gz")
    rows = rows[(rows.task == task) & (rows.model == model) & (rows.instruction_of == told)]
    return rows.groupby("robot")["return"].mean()


def cube(task: str, arm: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(steps, returns[seed, robot, step], robots)`` with the many-draw start at step 0."""
    frame = curves(task, arm)
    first = start(task, arm)
    if first is not None:
        frame = frame[frame.timesteps > 0]
        zero = pd.DataFrame([(s, 0, r, v) for s in frame.seed.unique() for r, v in first.items()], columns=frame.columns)
        frame = pd.concat([zero, frame])
    table = frame.pivot_table(index=["seed", "robot"], columns="timesteps", values="return")
    seeds, robots = sorted(table.index.get_level_values(0).unique()), sorted(table.index.get_level_values(1).unique())
    values = np.stack([table.loc[s].reindex(robots).to_numpy() for s in seeds])
    return table.columns.to_numpy(float), values, robots


def resampled(values: np.ndarray, robot_draws: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The mean curve of each bootstrap draw: seeds resampled independently, robots by the shared draws."""
    seeds = rng.integers(0, values.shape[0], (len(robot_draws), values.shape[0]))
    return np.stack([values[s][:, r].mean(axis=(0, 1)) for s, r in zip(seeds, robot_draws)])


def hold(steps: np.ndarray, curve: np.ndarray, level: float) -> float:
    held = steps_to_hold(steps, curve, level)
    return np.inf if held is None else held


def ratio(reference: float, arm: float) -> float:
    """How many times fewer steps the arm needs than the reference (inf: from the start; 0: never)."""
    return np.inf if arm == 0 else 0.0 if np.isinf(arm) else reference / arm


def training_log(task: str, arm: str) -> pd.DataFrame:
    """One row per PPO update of every seed: stochastic training return and approximate KL."""
    if arm in OURS:
        log = pd.read_csv(HERE / "training.csv.gz")
        log = log[log.variant == f"{arm}-{task}"]
    else:
        name = {
            "divmorph": f"training-{task}-gates-closest-{task}-closest",
            "closest": f"training-{task}-gates-closest-{task}-closest",
            "distilled": f"training-{task}-distilled",
            "scratch": "training-scratch",
        }[arm]
        log = pd.read_csv(RACE / f"{name}.csv.gz")
        log = log[(log.task == task) & (log.arm == arm)]
    return log


def stochastic(task: str, arm: str) -> np.ndarray:
    """Per seed: mean stochastic training return of the last ``WINDOW`` updates minus the first ``WINDOW``."""
    gains = []
    for _, run in training_log(task, arm).sort_values("timesteps").groupby("seed"):
        returns = run.training_return.to_numpy()
        gains.append(returns[-WINDOW:].mean() - returns[:WINDOW].mean())
    return np.array(gains)


def fmt_steps(value: float) -> str:
    return "never" if np.isinf(value) else "step 0" if value == 0 else f"{value / 1e3:.0f}k"


def fmt_ratio(value: float) -> str:
    return "from the start" if np.isinf(value) else "never" if value == 0 else f"{value:.1f}x"


def has_runs(task: str, arm: str) -> bool:
    return arm not in OURS or not curves(task, arm).empty


def task_rows(task: str, rng: np.random.Generator) -> tuple[list[str], dict[str, tuple[np.ndarray, np.ndarray]]]:
    data = {arm: cube(task, arm) for arm in ARMS if has_runs(task, arm)}
    robots = sorted(set.intersection(*(set(r) for _, _, r in data.values())))
    robot_draws = rng.integers(0, len(robots), (DRAWS, len(robots)))
    means, draws = {}, {}
    for arm, (steps, values, arm_robots) in data.items():
        values = values[:, [arm_robots.index(r) for r in robots]]
        means[arm] = (steps, values.mean(axis=(0, 1)))
        draws[arm] = (steps, resampled(values, robot_draws, rng), values)
    rows = []
    for arm in data:
        steps, boot, values = draws[arm]
        gain = values[:, :, -1] - values[:, :, 0]  # (seeds, robots)
        gain_lo, gain_hi = run_interval(gain)
        reading = "learns" if gain_lo > 0 else "loses" if gain_hi < 0 else "neither, within noise"
        readings = []
        for reference in ("scratch", "closest"):
            if reference == arm:
                readings.append(f"{fmt_steps(hold(*means[arm], means[arm][1][-1]))}: the reference")
                continue
            ref_steps, ref_boot, _ = draws[reference]
            level, own = means[reference][1][-1], hold(*means[reference], means[reference][1][-1])
            mine = hold(steps, means[arm][1], level)
            # each draw: the reference's own final as the level, its steps and the arm's to hold it
            ratios = np.array([ratio(hold(ref_steps, r, r[-1]), hold(steps, b, r[-1])) for r, b in zip(ref_boot, boot)])
            lo, hi = np.percentile(ratios, [2.5, 97.5], method="nearest")
            readings.append(f"{fmt_steps(mine)}: {fmt_ratio(ratio(own, mine))} [{fmt_ratio(lo)}, {fmt_ratio(hi)}]")
        noisy = stochastic(task, arm)
        noisy_lo, noisy_hi = seed_interval(noisy)
        held_out = curves(task, arm, "novel").pivot_table(index=["seed", "robot"], columns="timesteps", values="return")
        held_gain = (held_out.iloc[:, -1] - held_out.iloc[:, 0]).unstack("robot").dropna(axis=1).to_numpy()
        held_lo, held_hi = run_interval(held_gain)
        kl = training_log(task, arm).approx_kl
        rows.append(
            f"| {task} | {LABELS[arm]} | {values.shape[0]} | {means[arm][1][0]:.1f} | {means[arm][1][-1]:.1f} "
            f"| {gain.mean():+.1f} [{gain_lo:+.1f}, {gain_hi:+.1f}] | {reading} | {readings[0]} | {readings[1]} "
            f"| {noisy.mean():+.1f} [{noisy_lo:+.1f}, {noisy_hi:+.1f}] "
            f"| {held_out.iloc[:, 0].mean():.1f} -> {held_out.iloc[:, -1].mean():.1f}: {held_gain.mean():+.1f} [{held_lo:+.1f}, {held_hi:+.1f}] "
            f"| {kl.mean():.4f} / {kl.median():.4f} / {kl.max():.3f} |"
        )
    return rows, means


def figure(all_means: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]) -> None:
    fig, axes = plt.subplots(1, len(all_means), figsize=(5.2 * len(all_means), 3.8), squeeze=False)
    for ax, (task, means) in zip(axes[0], all_means.items()):
        for arm, (steps, curve) in means.items():
            ax.plot(steps / 1e3, curve, marker="o", lw=2.2 if arm in OURS else 1.2, color=COLORS[arm], label=LABELS[arm])
        ax.set_title(f"{task} (training robots)")
        ax.set_xlabel("env steps on the task (thousands)")
        ax.set_ylabel("deterministic return (mean over robots, seeds)")
        ax.grid(alpha=0.3)
    for ax in axes[0]:
        ax.legend(fontsize=6, loc="lower right")
    fig.suptitle(
        "Confirmation of the candidate recipe, and the controls on Escape (3 seeds x 602,112 steps; step 0 = many-draw start)", fontsize=9
    )
    fig.tight_layout()
    save_png(fig, HERE / "confirm.png")
    plt.close(fig)


def main() -> None:
    rng = np.random.default_rng(0)
    lines = [
        "| task | arm | seeds | start | last | last - start [95% CI] | reading | holds scratch's final from: "
        "x fewer steps [95% CI] | holds MetaMorph→'s final from: x fewer steps [95% CI] | stochastic training return, "
        "last - first 30 updates [95% CI] | held-out robots: step 0 -> last: last - step 0 [95% CI] | approx. KL per update: mean / median / largest |",
        "|---|---|---:|---:|---:|---|---|---|---|---|---|---:|",
    ]
    all_means = {}
    for task in TASKS:
        rows, all_means[task] = task_rows(task, rng)
        lines.extend(rows)
    text = "\n".join(lines)
    (HERE / "confirm.md").write_text(text + "\n")
    print(text)
    figure(all_means)


if __name__ == "__main__":
    main()
