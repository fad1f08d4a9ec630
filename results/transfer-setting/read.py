"""Read the setting ladder on the development task by its rule (``rule.md``): does each arm rise in each setting?

    python results/transfer-setting/read.py                      # every setting packed here -> reading.md, curves.png
    python results/transfer-setting/read.py --runs S1=/work/ladder/S1   # a setting still in its run folder

A setting's runs are kept as ``tools/pack_transfer_runs.py`` packs them (``<setting>/<variant>/transfer/
ManipulateBox/<arm>/seed-<n>/eval.csv.gz``), its many-draw starts as ``<setting>/baseline.json`` (written by
``finetune_known_task.py --baseline-seeds 5``). An arm **rises** when its last evaluation minus its start, per
robot of the curve's training robots, has a 95% interval wholly above 0, the interval resampling training
runs (seeds) and robots within them: MetaMorph→ against the mean of its starting model over the evaluation
seeds (one start for every run: :func:`~divmorph.pipeline.metrics.paired_run_interval`), scratch against
each run's own step 0 (its random init differs per run: :func:`~divmorph.pipeline.metrics.run_interval` of
the per-run change).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from divmorph.pipeline.metrics import paired_run_interval, run_interval

STUDY = Path(__file__).resolve().parent
TASK = "ManipulateBox"
ARMS = {"closest": "MetaMorph→ (closest teacher, fine-tuned)", "scratch": "MetaMorph from scratch"}
SETTINGS = ["S1", "S2", "S3", "S4"]


def eval_table(folder: Path) -> pd.DataFrame | None:
    """One run's evaluations on the training robots: rows (timesteps, robot) -> mean return over its episodes."""
    for name in ("eval.csv.gz", "eval.csv"):
        if (folder / name).is_file():
            frame = pd.read_csv(folder / name)
            frame = frame[frame.split == "train"]
            return frame.groupby(["timesteps", "robot"])["return"].mean().unstack("robot")
    return None


def runs_of(setting: Path, arm: str) -> dict[int, pd.DataFrame]:
    """``{seed: evaluations}`` of the finished runs of ``arm`` under ``setting`` (packed or in a run folder)."""
    found = {}
    for done in sorted(setting.glob(f"**/transfer/{TASK}/{arm}/seed-*/done.json")):
        table = eval_table(done.parent)
        if table is not None:
            found[int(done.parent.name.removeprefix("seed-"))] = table
    return found


def baseline(setting: Path, arm: str) -> pd.Series | None:
    """Robot -> the starting model's mean over the evaluation seeds (``None`` when not measured)."""
    for path in (setting / "baseline.json", *setting.glob("*/baseline.json")):
        if path.is_file():
            saved = json.loads(path.read_text())
            if arm in saved:
                return pd.DataFrame(saved[arm]).mean(axis=1)
    return None


def read_setting(setting: Path) -> list[dict[str, object]]:
    rows = []
    for arm, label in ARMS.items():
        runs = runs_of(setting, arm)
        if not runs:
            continue
        robots = sorted(set.intersection(*(set(table.columns) for table in runs.values())))
        last = np.stack([table.loc[table.index.max(), robots].to_numpy() for table in runs.values()])
        first = np.stack([table.loc[table.index.min(), robots].to_numpy() for table in runs.values()])
        steps = max(table.index.max() for table in runs.values())
        start = baseline(setting, arm) if arm == "closest" else None
        if start is not None:
            start_row = start.reindex(robots).to_numpy()[None]
            change = last.mean() - start_row.mean()
            low, high = paired_run_interval(last, start_row)
            start_text = f"{start_row.mean():.1f} (many draws)"
        else:
            change = (last - first).mean()
            low, high = run_interval(last - first)
            start_text = f"{first.mean():.1f} (each run's step 0)"
        rows.append(
            dict(
                setting=setting.name,
                arm=label,
                seeds=len(runs),
                steps=int(steps),
                start=start_text,
                last=f"{last.mean():.1f}",
                change=f"{change:+.1f} [{low:+.1f}, {high:+.1f}]",
                rises="yes" if low > 0 else ("falls" if high < 0 else "no"),
                straddles_by_less_than_half_width=bool(low <= 0 < high and -low < (high - low) / 2),
            )
        )
    return rows


def curves_figure(settings: dict[str, Path], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(settings), figsize=(5 * len(settings), 3.6), squeeze=False)
    for ax, (name, folder) in zip(axes[0], settings.items()):
        for (arm, label), colour in zip(ARMS.items(), ("tab:blue", "tab:orange")):
            for i, table in enumerate(runs_of(folder, arm).values()):
                ax.plot(table.index / 1e6, table.mean(axis=1), color=colour, alpha=0.8, label=label if i == 0 else None)
            start = baseline(folder, arm)
            if start is not None:
                ax.axhline(start.mean(), color=colour, ls=":", lw=1)
        ax.set_title(f"{name}: {TASK}, training robots")
        ax.set_xlabel("env steps (millions)")
        ax.set_ylabel("mean return (deterministic)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="*", default=[], metavar="SETTING=FOLDER", help="read a setting from its run folder")
    parser.add_argument("--out", type=Path, default=STUDY, help="where reading.md and curves.png go")
    args = parser.parse_args(argv)
    settings = {name: STUDY / name for name in SETTINGS if (STUDY / name).is_dir()}
    settings.update({name: Path(folder) for name, folder in (item.split("=", 1) for item in args.runs)})
    rows = [row for name in SETTINGS if name in settings for row in read_setting(settings[name])]
    if not rows:
        raise SystemExit("no finished run: pack a setting here or name its run folder with --runs")
    lines = [
        "| setting | arm | seeds | steps | start | last evaluation | change [95% CI, runs and robots] | rises |",
        "|---|---|---:|---:|---|---:|---|---|",
    ]
    lines += [
        f"| {r['setting']} | {r['arm']} | {r['seeds']} | {r['steps']:,} | {r['start']} | {r['last']} | {r['change']} | {r['rises']} |"
        for r in rows
    ]
    straddling = [f"{r['setting']} {r['arm']}" for r in rows if r["straddles_by_less_than_half_width"] and r["seeds"] < 5]
    if straddling:
        lines += ["", "The rule asks for 2 more seeds before reading: " + ", ".join(straddling) + "."]
    text = "\n".join(lines)
    (args.out / "reading.md").write_text(text + "\n")
    curves_figure(settings, args.out / "curves.png")
    print(text)
    return text


if __name__ == "__main__":
    main()
