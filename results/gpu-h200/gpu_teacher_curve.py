"""The paper-size FT teachers trained on the GPU beside the CPU run's FT teacher, on the 100 official
training robots: training return against environment steps and against gradient steps.

Every curve is SB3's ``rollout/ep_rew_mean`` (stochastic policy, the mean over the last 100 finished
episodes of all robots) from the runs' ``progress.csv``: the same quantity, logged the same way, for
all three. Deterministic evaluations are elsewhere (results/gpu-h200/README.md).

    python results/gpu-h200/gpu_teacher_curve.py     # writes results/gpu-h200/ft_teacher_curve.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from divmorph.pipeline.figures import save_png  # noqa: E402
from divmorph.pipeline.files import read_csv_rows  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results"

#: (label, progress file, line style, minibatch size, epochs): the GPU sessions' teachers and the CPU
#: run's FT teacher. PPO makes epochs x (rollout / minibatch) gradient steps per rollout, i.e.
#: epochs / minibatch per sample (SB3's train/n_updates counts epochs, not gradient steps).
CURVES = [
    (
        "GPU, paper size, session 1 (12,800 envs x 16 steps, minibatch 8,192 x 4 epochs)",
        RESULTS / "gpu-h200" / "ft_teacher_progress.csv",
        "-",
        8192,
        4,
    ),
    (
        "GPU, paper size, session 3 (12,800 envs x 16 steps, minibatch 4,096 x 2 epochs)",
        RESULTS / "gpu-h200" / "session-3" / "ft_teacher_progress.csv",
        "-",
        4096,
        2,
    ),
    (
        "CPU run cpu100, width 32 (16 envs x 512 steps, minibatch 2,048 x 4 epochs)",
        RESULTS / "cpu100" / "teachers" / "FT" / "logs" / "run-0" / "progress.csv.gz",
        "--",
        2048,
        4,
    ),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=RESULTS / "gpu-h200" / "ft_teacher_curve.png", help="figure to write")
    args = parser.parse_args()

    fig, (by_samples, by_updates) = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for label, path, style, minibatch, epochs in CURVES:
        color = None
        # one line per training segment: a resumed run starts a fresh window of finished episodes
        for segment in read_progress(path):
            steps = [row["time/total_timesteps"] for row in segment]
            returns = [row["rollout/ep_rew_mean"] for row in segment]
            (line,) = by_samples.plot([s / 1e6 for s in steps], returns, style, color=color, label=label if color is None else None)
            color = line.get_color()
            by_updates.plot([s * epochs / minibatch for s in steps], returns, style, color=color)
    by_samples.set_xlabel("environment steps (millions)")
    by_samples.set_ylabel("training return (stochastic, mean of last 100 episodes)")
    by_updates.set_xlabel("gradient steps (PPO minibatch updates; log scale)")
    by_updates.set_xscale("log")
    for ax in (by_samples, by_updates):
        ax.grid(alpha=0.3)
    by_samples.legend(fontsize=7, loc="upper left")
    fig.suptitle("FT teachers on the 100 official training robots: GPU (paper size) vs CPU run (width 32)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, args.out)  # a 256-colour palette: a third of the RGBA file in the tracked tree
    print(f"wrote {args.out}")


def read_progress(path: Path) -> list[list[dict[str, float]]]:
    """The rows of an SB3 ``progress.csv`` (plain or gzipped) that logged a training return, as floats,
    split into training segments (a new segment where the step count goes back or a ``segment``
    column changes: a run resumed from its checkpoint)."""
    segments: list[list[dict[str, float]]] = []
    last_steps, last_segment = float("-inf"), None
    for row in read_csv_rows(path):
        if not row.get("rollout/ep_rew_mean"):
            continue
        steps = float(row["time/total_timesteps"])
        if not segments or row.get("segment") != last_segment or steps <= last_steps:
            segments.append([])
        segments[-1].append({"time/total_timesteps": steps, "rollout/ep_rew_mean": float(row["rollout/ep_rew_mean"])})
        last_steps, last_segment = steps, row.get("segment")
    return segments


if __name__ == "__main__":
    main()
