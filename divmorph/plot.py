"""Learning curves of training runs as labelled PNGs, headless: ``divmorph plot``.

``rl_zoo3.plots.plot_train`` opens a window (without a display it exits 0 and writes nothing), and
``divmorph report`` reads pipeline run folders only. This reads what any of these leave behind::

    divmorph plot logs/ppo/Unimal-FT-v0_1                       # an rl-zoo run (its *.monitor.csv files)
    divmorph plot logs/ppo/Unimal-FT-v0_1 logs/ppo/Unimal-FT-v0_2 --out ft.png --window 20
    divmorph plot runs/demo/teachers/FT runs/demo/teachers/VT   # pipeline stages (logs/run-*/progress.csv)

A folder's curve comes from SB3 ``Monitor`` files (``*monitor.csv``, one row per finished episode:
return against the env steps taken so far, smoothed over ``--window`` episodes) or, when there are
none, from SB3 ``progress.csv`` logs (``rollout/ep_rew_mean`` against ``time/total_timesteps``).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np


class PlotError(ValueError):
    """A folder holds no learning curve this module can read."""


def learning_curve(folder: str | Path, window: int = 10) -> tuple[np.ndarray, np.ndarray, str]:
    """(env steps, mean episode return, source) of one training run.

    :param folder: an rl-zoo run folder or any folder with SB3 Monitor files, or a pipeline stage
        folder with SB3 ``progress.csv`` logs (searched recursively).
    :param window: episodes per moving average of the Monitor returns (1 = raw).
    :raises PlotError: the folder does not exist or holds neither kind of file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise PlotError(f"no such folder: {folder}")
    monitors = sorted(folder.rglob("*monitor.csv"))
    if monitors:
        # line 1 of a Monitor file is its JSON header; then one row per episode (r, l, t)
        episodes = sorted(
            (
                (float(row["t"]), float(row["l"]), float(row["r"]))
                for f in monitors
                for row in csv.DictReader(f.read_text().splitlines()[1:])
            ),
        )
        steps = np.cumsum([length for _, length, _ in episodes]).astype(float)
        returns = np.array([value for _, _, value in episodes], dtype=float)
        if window > 1 and len(returns) >= window:
            returns = np.convolve(returns, np.ones(window) / window, mode="valid")
            steps = steps[window - 1 :]
        smoothing = f", mean of {window}" if window > 1 else ""
        return steps, returns, f"{len(monitors)} Monitor file(s), {len(episodes)} episodes{smoothing}"
    logs = sorted({*folder.rglob("progress.csv"), *folder.rglob("progress.csv.gz")})  # (a recorded run ships them packed)
    if logs:
        from divmorph.pipeline.files import read_csv_rows  # (the pipeline's imports only when a stage is read)

        # SB3 logs the episode return only after the first episodes have ended: rows without it are skipped
        points = sorted(
            (float(row["time/total_timesteps"]), float(row["rollout/ep_rew_mean"]))
            for f in logs
            for row in read_csv_rows(f)
            if row.get("rollout/ep_rew_mean") not in (None, "")
        )
        return (
            np.array([step for step, _ in points], dtype=float),
            np.array([value for _, value in points], dtype=float),
            f"{len(logs)} progress.csv log(s): rollout/ep_rew_mean, mean of SB3's last 100 episodes",
        )
    raise PlotError(
        f"{folder} holds no SB3 Monitor files (*monitor.csv) and no progress.csv logs; "
        "train with a Monitor-wrapped env (rl-zoo does) or point at a pipeline stage folder"
    )


def plot_learning_curves(folders: list[str | Path], out: str | Path, window: int = 10, title: str | None = None) -> Path:
    """Plot the learning curve of every folder into one PNG (headless) and return its path.

    :param folders: training runs (see :func:`learning_curve`); each is one line, labelled by its name.
    :param out: the PNG to write (parent folders are created).
    :param window: episodes per moving average of Monitor returns.
    :param title: figure title (default: the folders' names).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [(Path(f), *learning_curve(f, window)) for f in folders]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for folder, steps, returns, source in curves:
        label = folder.name if folder.name not in ("", ".") else str(folder)
        ax.plot(steps, returns, label=f"{label} ({source})", linewidth=1.4)
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(title or ", ".join(Path(f).name for f in folders), fontsize=10)
    ax.grid(alpha=0.3)
    # Below the axes, so it never covers the curves.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), fontsize=8, frameon=False, ncol=1)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``plot`` arguments (shared by ``divmorph plot`` and ``python -m divmorph.plot``)."""
    parser.add_argument("folders", nargs="+", help="rl-zoo run folders (logs/ppo/Unimal-FT-v0_1), Monitor folders or pipeline stages")
    parser.add_argument("--out", default="learning_curves.png", help="PNG to write (default: learning_curves.png)")
    parser.add_argument("--window", type=int, default=10, help="episodes per moving average of Monitor returns (default 10)")
    parser.add_argument("--title", default=None, help="figure title (default: the folders' names)")


def run(args: argparse.Namespace) -> int:
    """:func:`plot_learning_curves` with errors printed as one line on stderr; the exit code."""
    if args.window < 1:
        print(f"plot: --window must be at least 1, got {args.window}", file=sys.stderr)
        return 2
    try:
        path = plot_learning_curves(args.folders, args.out, args.window, args.title)
    except PlotError as error:
        print(f"plot: {error}", file=sys.stderr)
        return 2
    print(f"[plot] {len(args.folders)} curve(s) -> {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m divmorph.plot``: same arguments as ``divmorph plot``."""
    parser = argparse.ArgumentParser(
        prog="python -m divmorph.plot", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
