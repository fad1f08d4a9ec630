"""The paper's figures from a run folder, each a PNG with the CSV of every number it plots.

``divmorph figure NAME`` writes one, ``divmorph report`` all those with data, into ``report/figures/``:

================  ==============================================================================
name              content
================  ==============================================================================
transfer-train    (Fig 3) transfer curves per novel task, deterministic return on the training
                  robots, every non-ablation arm, mean over seeds with a ±1 sd band
transfer-novel    (Fig 4) the same on the novel robots (never trained on)
deployment        (Fig 5) single-agent deployment: returns of the teacher, the HyperDistill MLP
                  (when that baseline ran) and the DivMorph compact actor on training and novel
                  robots, and their parameter counts
ablation          (Fig 6) DivMorph and its ablations, both robot splits
gates             (Figs 7-8) task-gate and morphology-gate correlation heatmaps
================  ==============================================================================

Transfer curves come from the runs' ``eval.csv`` (:mod:`divmorph.pipeline.curves`, profile key
``transfer.eval_every``); the deployment bars from ``evaluate/returns.csv`` and the export
reports. The DivMorph compact actor's returns are the student's: export checks that the compact
actor computes the student's actions (max |diff| <= 1e-5), and the evaluation rolls out the student.
"""

from __future__ import annotations

import io
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from divmorph.pipeline.arms import ABLATION_ARMS, ARMS, MAIN_ARMS  # noqa: E402
from divmorph.pipeline.config import ConfigError, Profile  # noqa: E402
from divmorph.pipeline.curves import (  # noqa: E402, F401 -- the metrics are written in curves; re-exported
    EVAL_FILE,
    METRIC_COLUMNS,
    eval_curve,
    read_eval,
    seed_curves,
    seed_robot_curves,
    task_metrics,
    write_metrics,
)
from divmorph.pipeline.folders import export_reports, transfer_tasks  # noqa: E402
from divmorph.pipeline.metrics import ArmMetrics, mean_curve, robot_interval  # noqa: E402
from divmorph.pipeline.files import atomic_save, log_file, read_csv_rows, write_csv  # noqa: E402
from divmorph.pipeline.robots import profile_robots, profile_splits, transfer_eval_robots  # noqa: E402
from divmorph.pipeline.students import STUDENTS  # noqa: E402

#: Resolution of every report PNG (figures and report/*.png): legible at the sizes they are drawn, and
#: small enough, with a 256-colour palette (:func:`save_png`), that the recorded runs' reports fit the
#: repository's size limit (tests/test_tree_size.py).
DPI = 80
#: Each figure's caption: what its lines, bands, bars and error bars are.
CAPTIONS = {
    "transfer-train": "deterministic return on the training robots during transfer (transfer.eval_robots of them, spread "
    "over the set); line = mean over seeds (each seed: mean over those robots and their episodes), band = ±1 sd over seeds",
    "transfer-novel": "the same on held-out robots (never trained on: novel, and out-of-distribution where recorded); band = ±1 sd over seeds",
    "deployment": "bars = mean over robots of deterministic episodes, error bars = sd over robots; sizes: stored actor "
    "weights, mean over exported robots (log scale)",
    "pareto": "each deployable actor's size (stored weights, mean over exported robots, log scale) against its mean "
    "deterministic return on the training robots, error bars = 95% bootstrap interval over robots; line = Pareto front",
    "ablation": "DivMorph and its ablations, deterministic return; line = mean over seeds, band = ±1 sd over seeds",
    "gates": "Pearson correlation of the gate vectors of two tasks (left) or two robots (right)",
}
FIGURES = tuple(CAPTIONS)
SPLIT_WORDS = {"train": "training robots", "novel": "novel robots", "ood": "out-of-distribution robots"}


def figures_folder(out: Path) -> Path:
    return Path(out) / "report" / "figures"


def save_png(fig, path: Path) -> None:
    """Write ``fig`` as a PNG atomically, at :data:`DPI`, in a 256-colour palette (a plot's lines,
    text and colour maps fit in it; a third of the RGBA file's size), and close it."""

    def write(target: Path) -> None:
        from PIL import Image

        buffer = io.BytesIO()
        fig.savefig(buffer, dpi=DPI, format="png", bbox_inches="tight")  # legends placed outside the axes stay in
        buffer.seek(0)
        with Image.open(buffer) as image:
            image.convert("RGB").quantize(256, dither=Image.Dither.NONE).save(target, format="PNG", optimize=True)

    atomic_save(path, write)
    plt.close(fig)


def outside_legend(ax) -> None:
    """The axes' legend below the axes, where it can never cover a curve."""
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)


def _save(fig, path: Path, rect: tuple[float, float, float, float] = (0, 0, 1, 1)) -> None:
    """Lay out (leaving ``rect``'s margins, e.g. for a figure legend) and write a PNG atomically."""
    fig.tight_layout(rect=rect)
    save_png(fig, path)


def metrics_table(metrics: list[ArmMetrics]) -> list[str]:
    """Markdown table of transfer metrics: means with their 95% bootstrap intervals."""
    lines = [
        "| task | arm | robots | seeds x robots | zero-shot return | final return | AUC (mean return) | level | "
        "steps to hold the level | speed-up vs scratch |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in metrics:
        level = "-" if m.level is None else f"{m.level:.1f}"
        lines.append(
            f"| {m.task} | {ARMS[m.arm].label} | {m.split} | {m.seeds} x {m.robots} | "
            f"{m.zero_shot:.1f} [{m.zero_shot_lo:.1f}, {m.zero_shot_hi:.1f}] | {m.final:.1f} [{m.final_lo:.1f}, {m.final_hi:.1f}] | "
            f"{m.auc:.1f} [{m.auc_lo:.1f}, {m.auc_hi:.1f}] | {level} | {m.steps_text()} | {m.efficiency_text()} |"
        )
    return lines


def _curves_figure(profile: Profile, out: Path, name: str, arms: tuple[str, ...], splits: tuple[str, ...], title: str) -> Path | None:
    tasks = transfer_tasks(profile, out)
    rows: list[dict[str, Any]] = []
    fig, axes = plt.subplots(len(splits), len(tasks), figsize=(5.2 * len(tasks), 3.9 * len(splits)), squeeze=False)
    for r, split in enumerate(splits):
        # the curves roll out transfer.eval_robots of the split (spread over it), eval_episodes each
        n_robots, n_split = len(transfer_eval_robots(profile, split)), len(profile_robots(profile, split))
        episodes = profile.transfer.eval_episodes
        spread = f" of {n_split}" if n_robots < n_split else ""
        for c, task in enumerate(tasks):
            ax = axes[r][c]
            seeds: set[int] = set()
            for arm in arms:
                curves = seed_curves(out, task, arm, split)
                if not curves:
                    continue
                seeds |= set(curves)
                steps, mean, sd = mean_curve(list(curves.values()))
                line = ax.plot(steps, mean, marker="o", markersize=3, label=f"{ARMS[arm].label} (n={len(curves)})")[0]
                ax.fill_between(steps, mean - sd, mean + sd, color=line.get_color(), alpha=0.2)
                rows += [
                    {
                        "figure": name,
                        "task": task,
                        "split": split,
                        "arm": arm,
                        "timesteps": int(x),
                        "mean_return": m,
                        "sd_return": s,
                        "seeds": " ".join(map(str, sorted(curves))),
                        "robots": n_robots,
                        "episodes": episodes,
                    }
                    for x, m, s in zip(steps, mean, sd)
                ]
            ax.set_xlabel("env steps")
            ax.set_ylabel(f"episode return (deterministic; {n_robots} robots x {episodes} episodes)")
            ax.set_title(f"{task}: {n_robots}{spread} {SPLIT_WORDS[split]}, seeds {sorted(seeds) or '-'}", fontsize=9)
            if ax.lines:
                outside_legend(ax)
    if not rows:
        plt.close(fig)
        return None
    fig.suptitle(title)
    folder = figures_folder(out)
    write_csv(
        folder / f"{name}.csv",
        rows,
        ["figure", "task", "split", "arm", "timesteps", "mean_return", "sd_return", "seeds", "robots", "episodes"],
    )
    _save(fig, folder / f"{name}.png")
    return folder / f"{name}.png"


def _read_csv(path: Path) -> list[dict[str, str]]:
    return read_csv_rows(path)  # (or its packed twin, <path>.gz)


DEPLOYED = {"teacher": "Teacher (MetaMorph)", "hyperdistill": "HyperDistill MLP", "student": "DivMorph compact actor"}


def _deployment_data(profile: Profile, out: Path) -> tuple[dict[str, str], dict[tuple[str, str, str], dict[str, list[float]]], dict] | None:
    """What the deployment figures show: ``(models and their labels, returns by (model, task, split)
    and robot, actor sizes by (model, task))``; ``None`` without an evaluation."""
    returns_file = Path(out) / "evaluate" / "returns.csv"
    if log_file(returns_file) is None:
        return None
    tasks = list(profile.teachers.tasks)
    deployed = dict(DEPLOYED)
    # students distilled with a deployment diversion are deployed too (export/<student>/...)
    deployed.update({f"student-{name}": f"DivMorph compact actor ({name})" for name in STUDENTS if name.startswith("deploy-")})
    groups: dict[tuple[str, str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in _read_csv(returns_file):
        if row["model"] in deployed and row["task"] in tasks:
            groups[(row["model"], row["task"], row["split"])][row["morphology"]].append(float(row["return"]))
    sizes: dict[tuple[str, str], list[int]] = defaultdict(list)
    for path in export_reports(out):
        r = json.loads(path.read_text())
        student = r.get("student", "divmorph")
        sizes[("student" if student == "divmorph" else f"student-{student}", r["task"])].append(r["compact_weights"])
        if student == "divmorph":
            sizes[("teacher", r["task"])].append(r["metamorph_folded_weights"])  # like for like: through the same folding
    for path in (Path(out) / "hyperdistill" / "export").glob("*/report.json"):
        r = json.loads(path.read_text())
        sizes[("hyperdistill", r["task"])].append(r["mlp_weights"])
    return deployed, groups, sizes


def deployment_figure(profile: Profile, out: Path) -> Path | None:
    """Fig 5: per training task, returns on training and novel robots, and parameter counts."""
    out = Path(out)
    data = _deployment_data(profile, out)
    if data is None:
        return None
    deployed, by_robot, sizes = data
    tasks = list(profile.teachers.tasks)
    groups = {key: [r for robot in robots.values() for r in robot] for key, robots in by_robot.items()}
    models = [m for m in deployed if any(key[0] == m for key in groups)]
    if not models:
        return None
    rows = []
    # one panel per task and robot split (tasks' returns differ in scale), sizes in a last column
    splits = profile_splits(profile)
    fig = plt.figure(figsize=(2.9 * len(tasks) + 4.5, 3.8 * len(splits)))
    grid = fig.add_gridspec(len(splits), len(tasks) + 1, width_ratios=[1] * len(tasks) + [1.6])
    x = np.arange(len(models))
    for r, split in enumerate(splits):
        n_robots = len(profile_robots(profile, split))
        for c, task in enumerate(tasks):
            ax = fig.add_subplot(grid[r, c])
            values = [groups.get((model, task, split), []) for model in models]
            means = [np.mean(v) if v else np.nan for v in values]
            sds = [np.std(v) if v else np.nan for v in values]
            colors = [f"C{i}" for i in range(len(models))]
            ax.bar(x, means, 0.7, yerr=sds, capsize=2, color=colors)
            rows += [
                {"panel": f"returns ({split} robots)", "model": model, "task": task, "value": m, "sd": sd, "n": len(v)}
                for model, m, sd, v in zip(models, means, sds, values)
            ]
            ax.set_xticks(x, [str(i + 1) for i in range(len(models))])
            ax.set_title(f"{task}, {n_robots} {SPLIT_WORDS[split]}", fontsize=8)
            if c == 0:
                ax.set_ylabel("episode return (deterministic)")
            if r == len(splits) - 1:
                ax.set_xlabel("model (legend)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=f"C{i}") for i in range(len(models))]
    fig.legend(handles, [f"{i + 1}: {deployed[m]}" for i, m in enumerate(models)], loc="lower center", ncol=min(len(models), 3), fontsize=8)
    ax = fig.add_subplot(grid[:, -1])
    size_tasks = [t for t in tasks if any((m, t) in sizes for m in models)]
    width = 0.8 / len(models)
    for i, model in enumerate(models):
        values = [np.mean(sizes[(model, t)]) if (model, t) in sizes else np.nan for t in size_tasks]
        ax.bar(np.arange(len(size_tasks)) + (i - (len(models) - 1) / 2) * width, values, width, color=f"C{i}")
        rows += [
            {"panel": "parameters (actor, one robot)", "model": model, "task": t, "value": v, "sd": "", "n": len(sizes.get((model, t), []))}
            for t, v in zip(size_tasks, values)
        ]
    ax.set_xticks(np.arange(len(size_tasks)), size_tasks, rotation=45)
    ax.set_yscale("log")
    ax.set_xlabel("training task (exported robots)")
    ax.set_ylabel("actor parameters (count, log scale)")
    ax.set_title("deployed actor size\n(MetaMorph folded like the compact actor)" + ("" if size_tasks else ": no exports"), fontsize=8)
    fig.suptitle(
        f"Single-agent deployment (profile {profile.name}, seed {profile.seed}): bars = mean over robots of "
        f"{profile.evaluate.episodes} deterministic episode(s) each, error bars = sd over robots",
        fontsize=10,
    )
    folder = figures_folder(out)
    write_csv(folder / "deployment.csv", rows, ["panel", "model", "task", "value", "sd", "n"])
    _save(fig, folder / "deployment.png", rect=(0, 0.07, 1, 0.95))
    return folder / "deployment.png"


def pareto_front(sizes: list[float], returns: list[float]) -> list[int]:
    """Indices of the points that no other point beats (as small or smaller and as good or better, one of
    them strictly), by increasing size: the best return each size buys."""
    points = sorted(range(len(sizes)), key=lambda i: (sizes[i], -returns[i]))
    front: list[int] = []
    for i in points:
        if not front or returns[i] > returns[front[-1]]:
            front.append(i)
    return front


def pareto_figure(profile: Profile, out: Path) -> Path | None:
    """Deployment's trade-off: per training task, each deployable actor's size against the return it
    keeps on the training robots (like for like: every size counted after the same folding)."""
    out = Path(out)
    data = _deployment_data(profile, out)
    if data is None:
        return None
    deployed, by_robot, sizes = data
    tasks = [t for t in profile.teachers.tasks if any((m, t) in sizes and (m, t, "train") in by_robot for m in deployed)]
    if not tasks:
        return None
    present = [m for m in deployed if any(key[0] == m for key in by_robot)]
    columns = min(len(tasks), 3)
    fig, axes = plt.subplots(-(-len(tasks) // columns), columns, figsize=(4.4 * columns, 3.6 * -(-len(tasks) // columns)), squeeze=False)
    rows = []
    for ax, task in zip(axes.flat, tasks):
        models = [m for m in deployed if (m, task) in sizes and (m, task, "train") in by_robot]
        x = [float(np.mean(sizes[(m, task)])) for m in models]
        per_robot = [np.array([np.mean(v) for v in by_robot[(m, task, "train")].values()]) for m in models]
        y = [float(v.mean()) for v in per_robot]
        for i, (model, values) in enumerate(zip(models, per_robot)):
            lo, hi = robot_interval(values)
            color = f"C{present.index(model)}"  # the deployment figure's colours
            ax.errorbar(
                x[i], y[i], yerr=[[max(y[i] - lo, 0.0)], [max(hi - y[i], 0.0)]], fmt="o", color=color, capsize=3, label=deployed[model]
            )
            rows.append({"task": task, "model": model, "parameters": x[i], "return": y[i], "lo": lo, "hi": hi, "robots": len(values)})
        front = pareto_front(x, y)
        ax.plot([x[i] for i in front], [y[i] for i in front], "k--", linewidth=0.8, zorder=0)
        for row in rows[-len(models) :]:
            row["pareto"] = models.index(row["model"]) in front
        ax.set_xscale("log")
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("actor parameters (count, log scale)")
        ax.set_ylabel("return, training robots")
    for ax in list(axes.flat)[len(tasks) :]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=8)
    fig.suptitle(
        f"Deployment: actor size against return\n(profile {profile.name}, seed {profile.seed}; "
        f"{profile.evaluate.episodes} deterministic episode(s) per robot)",
        fontsize=10,
    )
    folder = figures_folder(out)
    write_csv(folder / "pareto.csv", rows, ["task", "model", "parameters", "return", "lo", "hi", "robots", "pareto"])
    _save(fig, folder / "pareto.png", rect=(0, 0.08, 1, 0.95))
    return folder / "pareto.png"


def _correlation(gates: np.ndarray) -> np.ndarray:
    centred = gates - gates.mean(1, keepdims=True)
    norms = np.linalg.norm(centred, axis=1, keepdims=True)
    norms[norms == 0] = 1
    unit = centred / norms
    return unit @ unit.T


def distinct_selections(gates: np.ndarray) -> int:
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
        ax.set_title(f"{title} ({len(labels)})")
        bar = fig.colorbar(image, ax=ax, fraction=0.046)
        bar.set_label("correlation of the gate vectors (Pearson)")
    fig.tight_layout()
    save_png(fig, target)


def gates_figure(profile: Profile, out: Path) -> Path | None:
    """Figs 7-8: correlation of task gates across the ten tasks and of morphology gates across robots."""
    gates_file = Path(out) / "evaluate" / "gates.npz"
    if not gates_file.is_file():
        return None
    with np.load(gates_file) as data:
        gates = {k: data[k] for k in data.files}
    folder = figures_folder(out)
    rows = []
    for key, labels in (("task_gates", gates["tasks"]), ("morphology_gates", gates["robots"])):
        corr = _correlation(gates[key])
        rows += [
            {"gates": key, "row": labels[i], "column": labels[j], "correlation": float(corr[i, j])}
            for i in range(len(labels))
            for j in range(len(labels))
        ]
    write_csv(folder / "gates.csv", rows, ["gates", "row", "column", "correlation"])
    plot_gates(gates, folder / "gates.png")
    return folder / "gates.png"


def make_figure(profile: Profile, out: Path, name: str) -> Path | None:
    """Write figure ``name`` (PNG + CSV); ``None`` when the run has no data for it yet.

    :raises ConfigError: unknown figure name.
    """
    seeds = list(profile.transfer.seeds)
    if name == "transfer-train":
        return _curves_figure(profile, out, name, MAIN_ARMS, ("train",), f"Transfer to novel tasks on the training robots (seeds {seeds})")
    # the held-out robots' curves: the novel robots and, where a run recorded them, the out-of-distribution ones
    held_out = tuple(
        split
        for split in profile_splits(profile)[1:]
        if any(seed_curves(out, task, arm, split) for task in transfer_tasks(profile, out) for arm in MAIN_ARMS)
    )
    if name == "transfer-novel":
        return _curves_figure(
            profile, out, name, MAIN_ARMS, held_out or ("novel",), f"Transfer to novel tasks on held-out robots (seeds {seeds})"
        )
    if name == "ablation":
        ablations = [arm for arm in ABLATION_ARMS if arm != "divmorph"]
        splits = ("train", *held_out)
        if not any(seed_curves(out, task, arm, split) for task in transfer_tasks(profile, out) for arm in ablations for split in splits):
            return None  # DivMorph alone is no ablation figure
        return _curves_figure(profile, out, name, ABLATION_ARMS, splits, f"Ablations of DivMorph (seeds {seeds})")
    if name == "deployment":
        return deployment_figure(profile, out)
    if name == "pareto":
        return pareto_figure(profile, out)
    if name == "gates":
        return gates_figure(profile, out)
    raise ConfigError(f"unknown figure {name!r}; figures: {list(FIGURES)}")


def make_figures(profile: Profile, out: Path) -> dict[str, Path]:
    """Every figure the run has data for: ``{name: png}``."""
    made = {name: make_figure(profile, out, name) for name in FIGURES}
    return {name: path for name, path in made.items() if path is not None}
