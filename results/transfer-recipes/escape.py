"""The candidate recipe's confirmation on Escape (``rule.md``'s addendum): the fixed-gate arm at a KL of 0.01
per update against its many-draw start, beside the race's Escape arms at their nominal rates; ``escape.md``.

    python results/transfer-recipes/escape.py

Starts: ``../novel-task-gates/returns.csv.gz`` (the DivMorph student under FT's gates, MetaMorph⚗ and the FT
teacher, 5 evaluation seeds x 3 episodes per robot); the race's runs: ``../transfer-pointnav/runs-600k/``.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from divmorph.pipeline.metrics import robot_interval

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent
#: label -> (curves: a race folder under runs-600k/ and its arm, or this study's variant; the start's model, told)
ARMS = {
    "fixed gates, KL 0.01 per update (this study)": ("K-Escape", "divmorph", "divmorph", "FT"),
    "fixed gates, nominal rate (the race)": ("Escape-gates-closest", "divmorph", "divmorph", "FT"),
    "MetaMorph→, nominal rate (the race)": ("Escape-closest", "closest", "teacher-FT", "Escape"),
    "MetaMorph⚗, nominal rate (the race)": ("Escape-distilled", "distilled", "distilled", "Escape"),
}


def curve(source: str, arm: str) -> pd.DataFrame:
    """Per (seed, timesteps, robot): mean deterministic return on the training curve robots."""
    if source.startswith("K-"):
        table = pd.read_csv(HERE / "curves.csv.gz")
        return table[(table.variant == source) & (table.split == "train")]
    parts = []
    for path in sorted((RESULTS / "transfer-pointnav" / "runs-600k" / source / "transfer" / "Escape" / arm).glob("seed-*/eval.csv.gz")):
        frame = pd.read_csv(path)
        frame = frame[frame.split == "train"].groupby(["timesteps", "robot"], as_index=False)["return"].mean()
        parts.append(frame.assign(seed=int(path.parent.name.split("-")[1])))
    return pd.concat(parts) if parts else pd.DataFrame(columns=["timesteps", "robot", "return", "seed"])


def start(model: str, told: str) -> pd.Series:
    rows = pd.read_csv(RESULTS / "novel-task-gates" / "returns.csv.gz")
    rows = rows[(rows.task == "Escape") & (rows.model == model) & (rows.instruction_of == told)]
    return rows.groupby("robot")["return"].mean()


def main() -> None:
    lines = [
        "| arm (Escape, 602,112 steps) | seeds | many-draw start | last evaluation | last against the start [95% CI] | reading | per seed |",
        "|---|---:|---:|---:|---|---|---|",
    ]
    for label, (source, arm, model, told) in ARMS.items():
        runs, first = curve(source, arm), start(model, told)
        if runs.empty or first.empty:
            lines.append(f"| {label} | 0 | – | – | not run | – | – |")
            continue
        last = runs[runs.timesteps == runs.groupby("seed").timesteps.transform("max")].set_index(["robot", "seed"])["return"]
        gain = (last - first.reindex(last.index.get_level_values(0)).to_numpy()).dropna()
        lo, hi = robot_interval(gain.to_numpy())
        reading = "learns" if lo > 0 else "loses" if hi < 0 else "neither, within noise"
        seeds = ", ".join(f"{value:+.1f}" for value in gain.groupby(level=1).mean())
        lines.append(
            f"| {label} | {runs.seed.nunique()} | {first.mean():.1f} | {last.mean():.1f} | {gain.mean():+.1f} [{lo:+.1f}, {hi:+.1f}] "
            f"| {reading} | {seeds} |"
        )
    text = "\n".join(lines)
    (HERE / "escape.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
