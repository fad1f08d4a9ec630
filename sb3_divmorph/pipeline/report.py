"""Stage 6 — report: learning curves, gate correlations, returns and sizes, as PNG + markdown.

Reads what the other stages wrote into the run folder (``logs/run-*/progress.csv`` of every
training run, ``evaluate/returns.csv`` and ``gates.npz``, ``export/*/report.json``) and writes
``report/curves.png``, ``report/gates.png``, ``report/returns.png`` and ``summary.md``.
"""

from __future__ import annotations

import csv
import json
import platform
import time
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sb3_divmorph.pipeline.config import Profile  # noqa: E402
from sb3_divmorph.pipeline.runs import atomic_save, atomic_write_text  # noqa: E402


def read_progress(folder: Path) -> dict[str, np.ndarray]:
    """All ``progress.csv`` rows of a training run (resumed attempts concatenated), by column."""
    rows: list[dict[str, str]] = []
    for log in sorted((folder / "logs").glob("run-*/progress.csv"), key=lambda p: int(p.parent.name.split("-")[1])):
        with open(log) as f:
            rows += list(csv.DictReader(f))
    columns: dict[str, list[float]] = defaultdict(list)
    keys = {k for row in rows for k in row}
    for row in rows:
        for key in keys:
            value = row.get(key, "")
            columns[key].append(float(value) if value not in ("", None) else np.nan)
    return {k: np.asarray(v) for k, v in columns.items()}


def _curve(ax, progress: dict[str, np.ndarray], key: str, label: str) -> bool:
    if key not in progress or "time/total_timesteps" not in progress:
        return False
    x, y = progress["time/total_timesteps"], progress[key]
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return False
    ax.plot(x[ok], y[ok], marker="o", markersize=3, label=label)
    return True


def plot_curves(profile: Profile, out: Path, target: Path) -> None:
    tasks = profile.transfer.tasks
    fig, axes = plt.subplots(1, 2 + len(tasks), figsize=(5 * (2 + len(tasks)), 3.8), squeeze=False)
    axes = axes[0]
    for task in profile.teachers.tasks:
        _curve(axes[0], read_progress(out / "teachers" / task), "rollout/ep_rew_mean", task)
    axes[0].set_title("teachers (PPO): episode return")
    student = read_progress(out / "student")
    for task in profile.teachers.tasks:
        _curve(axes[1], student, f"distill/kl/{task}", task)
    axes[1].set_yscale("log")
    axes[1].set_title("distillation: KL(teacher || student)")
    for ax, task in zip(axes[2:], tasks):
        for arm, label in (("divmorph", "DivMorph transfer"), ("scratch", "MetaMorph from scratch")):
            _curve(ax, read_progress(out / "transfer" / task / arm), "rollout/ep_rew_mean", label)
        ax.set_title(f"transfer to {task}: episode return")
    for ax in axes:
        ax.set_xlabel("env steps")
        if ax.lines:
            ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_save(target, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)


def _correlation(gates: np.ndarray) -> np.ndarray:
    centred = gates - gates.mean(1, keepdims=True)
    norms = np.linalg.norm(centred, axis=1, keepdims=True)
    norms[norms == 0] = 1
    unit = centred / norms
    return unit @ unit.T


def _distinct(gates: np.ndarray) -> int:
    return len({tuple(row) for row in (gates > 0)})


def plot_gates(gates: dict[str, np.ndarray], target: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2))
    for ax, key, labels, title in (
        (axes[0], "task_gates", gates["tasks"], "task-gate correlation across tasks"),
        (axes[1], "morphology_gates", gates["robots"], "morphology-gate correlation across robots"),
    ):
        corr = _correlation(gates[key])
        image = ax.imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
        ax.set_xticks(range(len(labels)), labels, rotation=90, fontsize=7)
        ax.set_yticks(range(len(labels)), labels, fontsize=7)
        ax.set_title(title)
        fig.colorbar(image, ax=ax, fraction=0.046)
    fig.tight_layout()
    atomic_save(target, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)


def read_returns(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def returns_table(rows: list[dict[str, str]]) -> tuple[list[str], dict[tuple[str, str, str], list[float]]]:
    groups: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for row in rows:
        groups[(row["model"], row["task"], row["split"])].append(float(row["return"]))
    lines = ["| model | task | train robots: return (mean ± sd, n) | novel robots: return |", "|---|---|---|---|"]
    for model, task in sorted({(m, t) for m, t, _ in groups}, key=lambda mt: (mt[1], mt[0])):
        cells = []
        for split in ("train", "novel"):
            values = groups.get((model, task, split), [])
            cells.append(f"{np.mean(values):.1f} ± {np.std(values):.1f} ({len(values)})" if values else "–")
        lines.append(f"| {model} | {task} | {cells[0]} | {cells[1]} |")
    return lines, groups


def plot_returns(groups: dict[tuple[str, str, str], list[float]], target: Path) -> None:
    keys = sorted({(m, t) for m, t, _ in groups}, key=lambda mt: (mt[1], mt[0]))
    fig, ax = plt.subplots(figsize=(max(6, 0.55 * len(keys)), 4))
    x = np.arange(len(keys))
    for offset, split in ((-0.2, "train"), (0.2, "novel")):
        means = [np.mean(groups.get((m, t, split), [np.nan])) for m, t in keys]
        sds = [np.std(groups.get((m, t, split), [np.nan])) for m, t in keys]
        ax.bar(x + offset, means, 0.4, yerr=sds, label=f"{split} robots", capsize=2)
    ax.set_xticks(x, [f"{t}\n{m}" for m, t in keys], rotation=90, fontsize=7)
    ax.set_ylabel("episode return (per robot)")
    ax.legend()
    fig.tight_layout()
    atomic_save(target, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)


def _fmt_steps(progress: dict[str, np.ndarray]) -> str:
    steps = progress.get("time/total_timesteps")
    return str(int(np.nanmax(steps))) if steps is not None and len(steps) else "?"


def report(profile: Profile, out: Path, command: str = "") -> str:
    """Write the report of run folder ``out`` and return the markdown summary."""
    out = Path(out)
    folder = out / "report"
    folder.mkdir(parents=True, exist_ok=True)
    lines = [
        f"# DivMorph pipeline — profile `{profile.name}`",
        "",
        f"- command: `{command or 'divmorph pipeline --profile ' + profile.name}`",
        f"- written {time.strftime('%Y-%m-%d %H:%M')} on {platform.node() or 'this machine'} "
        f"({platform.processor() or platform.machine()}), seed {profile.seed}, device {profile.device}",
        f"- robots: first {profile.train_robots or 'all'} of `{profile.train_set}`, first {profile.novel_robots or 'all'} "
        f"of `{profile.novel_set}` (never a training robot); "
        f"episodes of at most {profile.max_episode_steps} steps",
        "",
        "## Stages",
        "",
        "| stage | output | env steps |",
        "|---|---|---|",
    ]
    for task in profile.teachers.tasks:
        lines.append(f"| teacher {task} (MetaMorph, PPO) | `teachers/{task}/model.zip` | {_fmt_steps(read_progress(out / 'teachers' / task))} |")
    lines.append(f"| DAgger distillation (DivMorph student) | `student/model.zip` | {_fmt_steps(read_progress(out / 'student'))} |")
    for task in profile.transfer.tasks:
        for arm in ("divmorph", "scratch"):
            if (out / "transfer" / task / arm / "done.json").is_file():
                lines.append(f"| transfer {task} ({arm}) | `transfer/{task}/{arm}/model.zip` | {_fmt_steps(read_progress(out / 'transfer' / task / arm))} |")

    plot_curves(profile, out, folder / "curves.png")
    lines += ["", "## Learning curves", "", "![curves](report/curves.png)", ""]
    for task in profile.transfer.tasks:
        finals = {}
        for arm in ("divmorph", "scratch"):
            progress = read_progress(out / "transfer" / task / arm)
            values = progress.get("rollout/ep_rew_mean", np.array([]))
            values = values[np.isfinite(values)]
            if len(values):
                finals[arm] = (values[-1], values.mean())
        if finals:
            cells = ", ".join(f"{arm}: last {v[0]:.1f}, mean over training {v[1]:.1f}" for arm, v in finals.items())
            lines.append(f"- transfer to {task} (training-episode return): {cells}")

    returns_file = out / "evaluate" / "returns.csv"
    if returns_file.is_file():
        table, groups = returns_table(read_returns(returns_file))
        plot_returns(groups, folder / "returns.png")
        lines += ["", "## Per-morphology evaluation (deterministic actions)", "", *table, "",
                  "Per-robot rows: `evaluate/returns.csv`.", "", "![returns](report/returns.png)"]
    gates_file = out / "evaluate" / "gates.npz"
    if gates_file.is_file():
        with np.load(gates_file) as data:
            gates = {k: data[k] for k in data.files}
        plot_gates(gates, folder / "gates.png")
        used = (gates["task_gates"] > 0).sum(0)
        lines += ["", "## Gates", "", "![gates](report/gates.png)", "",
                  f"Task tailors selected by at least one of the 10 instructions: {int((used > 0).sum())} of {len(used)}; "
                  f"distinct task-tailor selections: {_distinct(gates['task_gates'])} among {len(gates['tasks'])} tasks; "
                  f"distinct morphology-tailor selections: {_distinct(gates['morphology_gates'])} among "
                  f"{len(gates['robots'])} robots (the correlation of two gate vectors that select the same top-k "
                  "tailors is close to 1 even when their weights differ)."]

    exports = sorted((out / "export").glob("*/report.json"))
    if exports:
        lines += ["", "## Deployment: pruned compact actors", "",
                  "| robot | task | exported from | MetaMorph actor (folded) | compact DivMorph | reduction (like for like) "
                  "| MetaMorph actor (unfolded) | folding alone | max abs diff | latency compact / student (ms, batch 1) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for path in exports:
            r = json.loads(path.read_text())
            lines.append(
                f"| {r['robot']} | {r['task']} | {r['source_label']} | {r['metamorph_folded_weights']:,} | {r['compact_weights']:,} | "
                f"{r['reduction_vs_metamorph']:.1f}x | {r['metamorph_actor_parameters']:,} | {r['folding_metamorph']:.2f}x | "
                f"{r['max_abs_diff']:.1e} | {r['latency_compact_ms']:.3f} / {r['latency_student_ms']:.3f} ({r['speedup_vs_student']:.1f}x) |"
            )
        lines += ["", "Like for like: the MetaMorph actor of the same task and sizes is exported through the same folding "
                  "(context rows, position embedding, padded tokens and encoders of observations the task lacks become "
                  "constants), so the reduction counts pruning only; 'folding alone' is what folding saves MetaMorph. "
                  "Baked normalisation statistics are not counted (both actors need them)."]
    summary = "\n".join(lines) + "\n"
    atomic_write_text(out / "summary.md", summary)
    return summary
