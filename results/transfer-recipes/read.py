"""Read the recipes' control (``rule.md``): each variant's last evaluation against its many-draw start,
beside the nominal-rate arms of ``../goal-range/`` (the same bounded goal, robots, episodes and starts);
the table of ``README.md`` and ``pointnav.png``.

    python results/transfer-recipes/read.py

Every variant starts from a model whose step-0 policy is one of ``../goal-range/``'s arms (F, K, S, A: the
DivMorph student under Patrol's gates; Km: MetaMorph⚗), so its many-draw start is that arm's
(``../goal-range/starts.csv``); the check below asserts each run's step-0 evaluation equals that arm's.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from divmorph.pipeline.figures import save_png  # noqa: E402
from divmorph.pipeline.metrics import run_interval  # noqa: E402

HERE = Path(__file__).resolve().parent
GOAL_RANGE = HERE.parent / "goal-range"
#: variant -> (label, the goal-range arm it starts as)
VARIANTS = {
    "D": ("fixed gates, nominal rate (goal-range)", "divmorph"),
    "M": ("MetaMorph⚗, nominal rate (goal-range)", "distilled"),
    "F": ("(a) every DivMorph weight, rotations frozen", "divmorph"),
    "K": ("(d) fixed gates, KL 0.01 per update", "divmorph"),
    "Km": ("(d) MetaMorph⚗, KL 0.01 per update", "distilled"),
    "S": ("(c) fixed gates, singular values only (FINE)", "divmorph"),
    # B = 0: the adapted student acts as the student does
    "A": ("(c) fixed gates, a zero-initialised adapter only (LoRA, width 4)", "divmorph"),
    # the restart changes the policy before step 0: its start is its own runs' step-0 evaluations
    "KIND": ("(c) fixed gates, task tailors restarted (KIND)", None),
}


def curves() -> pd.DataFrame:
    """Training-robot curves of every variant: this study's and the two nominal-rate arms of goal-range."""
    mine = pd.read_csv(HERE / "curves.csv.gz")
    theirs = pd.read_csv(GOAL_RANGE / "curves.csv.gz")
    theirs = theirs[theirs.arm.isin(["divmorph", "distilled"])]
    theirs = theirs.assign(variant=theirs.arm.map({"divmorph": "D", "distilled": "M"})).drop(columns=["arm", "task"])
    return pd.concat([mine, theirs])


def check_starts(table: pd.DataFrame) -> None:
    """Each run's step-0 evaluation is its goal-range arm's, episode for episode (the same policy and episodes)."""
    first = table[table.timesteps == 0].set_index(["split", "robot", "seed"])
    for variant, (_, arm) in VARIANTS.items():
        if variant in ("D", "M") or arm is None or variant not in set(table.variant):
            continue
        reference = {"divmorph": "D", "distilled": "M"}[arm]
        mine, theirs = first[first.variant == variant]["return"], first[first.variant == reference]["return"]
        joined = pd.concat([mine, theirs], axis=1, join="inner").dropna()
        assert len(joined) and np.allclose(joined.iloc[:, 0], joined.iloc[:, 1], atol=1e-2), f"{variant} does not start as {reference}"


def training_columns(variant: str) -> tuple[str, str]:
    """The stochastic training return PPO optimises (the peers' curve: the mean of the last 100 sampled
    episodes), first and last 30 updates per seed, and the mean approximate KL per update."""
    if variant in ("D", "M"):
        log = pd.read_csv(GOAL_RANGE / "training.csv.gz")
        log = log[log.arm == VARIANTS[variant][1]]
    else:
        log = pd.read_csv(HERE / "training.csv.gz")
        log = log[log.variant == variant]
    if log.empty:
        return "–", "–"
    pairs = [f"{run.training_return.head(30).mean():.0f} / {run.training_return.tail(30).mean():.0f}" for _, run in log.groupby("seed")]
    return "; ".join(pairs), f"{log.approx_kl.mean():.3f}"


def against(last: pd.Series, start: pd.Series) -> np.ndarray:
    """Seeds x robots: each run's last evaluation minus the robot's start (robots every seed has), for an
    interval over training runs and robots (a run's robots share its policy: they are not independent draws)."""
    return (last.unstack("robot") - start.reindex(last.index.unique("robot")).to_numpy()).dropna(axis=1).to_numpy()


def main() -> None:
    table = curves()
    check_starts(table)
    starts = pd.read_csv(GOAL_RANGE / "starts.csv", index_col="robot")
    lines = [
        "| variant (PointNav, goal_range 10, 3 seeds x 602,112 steps) | seeds | many-draw start | last evaluation | last against the start [95% CI] | reading | held-out robots: step 0 -> last | stochastic training return, first / last 30 updates (per seed) | approx. KL per update |",
        "|---|---:|---:|---:|---|---|---|---|---|",
    ]
    figure, ax = plt.subplots(figsize=(7.5, 4.2))
    train = table[table.split == "train"]
    for variant, (label, arm) in VARIANTS.items():
        runs = train[train.variant == variant]
        if runs.empty:
            lines.append(f"| {label} | 0 | – | – | not run | – | – | – | – |")
            continue
        own = runs[runs.timesteps == 0].groupby("robot")["return"].mean()
        start = starts[arm] if arm is not None else own
        last_step = runs.groupby("seed").timesteps.transform("max")
        last = runs[runs.timesteps == last_step].set_index(["robot", "seed"])["return"]
        change = against(last, start)
        lo, hi = run_interval(change)
        reading = "learns" if lo > 0 else "loses" if hi < 0 else "neither, within noise"
        seeds = runs.seed.nunique()
        stochastic, kl = training_columns(variant)
        held_out = table[(table.split == "novel") & (table.variant == variant)]
        ends = held_out.groupby("seed").timesteps.transform("max")
        novel = f"{held_out[held_out.timesteps == 0]['return'].mean():.0f} -> {held_out[held_out.timesteps == ends]['return'].mean():.0f}"
        lines.append(
            f"| {label} | {seeds} | {start.mean():.0f} | {last.mean():.0f} | {change.mean():+.0f} [{lo:+.0f}, {hi:+.0f}] | {reading} "
            f"| {novel} | {stochastic} | {kl} |"
        )
        if arm is None:  # the rule's second reading: above the un-restarted student's start?
            above = against(last, starts["divmorph"])
            lo, hi = run_interval(above)
            lines.append(
                f"| {label}: last against the un-restarted start | {seeds} | {starts['divmorph'].mean():.0f} | {last.mean():.0f} "
                f"| {above.mean():+.0f} [{lo:+.0f}, {hi:+.0f}] | {'useful' if lo > 0 else 'not useful'} | | | |"
            )
        mean = runs.groupby("timesteps")["return"].mean()
        steps = mean.index.to_numpy() / 1e3
        values = np.r_[start.mean(), mean.to_numpy()[1:]]
        ax.plot(steps, values, marker="o", label=f"{label} ({seeds} seeds)", linestyle="--" if variant in ("D", "M") else "-")
    ax.set_xlabel("PPO env steps (thousands)")
    ax.set_ylabel("deterministic return, 20 training robots\n(mean over seeds x 5 episodes; step 0: 15 per robot)")
    ax.set_title("PointNav fine-tuning recipes, goal bounded at 10 m", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    figure.tight_layout()
    save_png(figure, HERE / "pointnav.png")
    text = "\n".join(lines)
    (HERE / "reading.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
