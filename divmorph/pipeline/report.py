"""Stage 6 — report: learning curves, gate correlations, returns and sizes, as PNG + markdown.

Reads what the other stages wrote into the run folder (``logs/run-*/progress.csv`` of every
training run, ``evaluate/returns.csv`` and ``gates.npz``, ``export/*/report.json``) and writes
``report/curves.png``, ``report/returns.png``, the paper's figures, the gate correlations among them
(``report/figures/*.png`` + ``.csv``, :mod:`divmorph.pipeline.figures`), the transfer metrics
(``transfer/<task>/metrics.csv``) and ``summary.md``.
"""

from __future__ import annotations

import json
import platform
import time
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from divmorph.pipeline.arms import ARMS  # noqa: E402
from divmorph.pipeline.config import Profile  # noqa: E402
from divmorph.pipeline.figures import (  # noqa: E402, F401 -- _correlation, plot_gates re-exported
    CAPTIONS,
    SPLIT_WORDS,
    _correlation,
    distinct_selections,
    make_figures,
    metrics_table,
    outside_legend,
    plot_gates,
    save_png,
    write_metrics,
)
from divmorph.pipeline.folders import export_reports, transfer_folder, transfer_seeds, transfer_tasks  # noqa: E402
from divmorph.pipeline.metrics import BOOTSTRAP, EFFICIENCY_FRACTION, interval, robot_interval  # noqa: E402
from divmorph.pipeline.provenance import RECORD, SUPERSEDED  # noqa: E402
from divmorph.pipeline.files import atomic_write_text, log_file, log_files, read_csv_rows, read_progress  # noqa: E402
from divmorph.pipeline.robots import SPLITS, transfer_eval_robots  # noqa: E402
from divmorph.pipeline.students import STUDENTS  # noqa: E402


def _curve(ax, progress: dict[str, np.ndarray], key: str, label: str) -> bool:
    if key not in progress or "time/total_timesteps" not in progress:
        return False
    x, y = progress["time/total_timesteps"], progress[key]
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return False
    ax.plot(x[ok], y[ok], marker="o", markersize=3, label=label)
    return True


def _robots_phrase(profile: Profile) -> str:
    return f"{profile.train_robots or 'all'} training robots of {profile.train_set}"


def plot_curves(profile: Profile, out: Path, target: Path) -> None:
    """Teachers' curves (one panel per task: their returns differ in scale), the distillation KL per
    task, and each transfer task's training-episode curves."""
    teachers, tasks = list(profile.teachers.tasks), transfer_tasks(profile, out)
    n = len(teachers) + 1 + len(tasks)
    columns = min(n, 4)
    fig, grid = plt.subplots(
        (n + columns - 1) // columns, columns, figsize=(4.6 * columns, 3.6 * ((n + columns - 1) // columns)), squeeze=False
    )
    axes = list(grid.flat)
    for ax, task in zip(axes, teachers):
        _curve(ax, read_progress(out / "teachers" / task), "rollout/ep_rew_mean", "MetaMorph teacher")
        ax.set_title(f"teacher {task} (PPO)", fontsize=9)
        ax.set_ylabel("episode return (training episodes)")
    kl_ax = axes[len(teachers)]
    student = read_progress(out / "student")
    for task in teachers:
        _curve(kl_ax, student, f"distill/kl/{task}", task)
    kl_ax.set_yscale("log")
    kl_ax.set_title("distillation into the DivMorph student", fontsize=9)
    kl_ax.set_ylabel("KL(teacher || student), nats per state")
    seed = profile.transfer.seeds[0]
    for ax, task in zip(axes[len(teachers) + 1 :], tasks):
        for arm in ARMS:
            _curve(ax, read_progress(transfer_folder(out, task, arm, seed)), "rollout/ep_rew_mean", ARMS[arm].label)
        ax.set_title(f"transfer to {task} (seed {seed})", fontsize=9)
        ax.set_ylabel("episode return (training episodes)")
    for ax in axes[:n]:
        ax.set_xlabel("env steps")
        if ax.lines:
            outside_legend(ax)
    for ax in axes[n:]:
        ax.axis("off")
    fig.suptitle(
        f"profile {profile.name}: learning curves on {_robots_phrase(profile)}, seed {profile.seed} "
        "(stochastic training episodes, one run each)",
        fontsize=10,
    )
    fig.tight_layout()
    save_png(fig, target)


def read_returns(path: Path) -> list[dict[str, str]]:
    """The rows of an evaluation's ``returns.csv`` (or its packed ``returns.csv.gz``)."""
    return read_csv_rows(path)


def returns_table(rows: list[dict[str, str]]) -> tuple[list[str], dict[tuple[str, str, str], list[float]]]:
    """The evaluation as a markdown table, and ``{(model, task, split): per-robot mean returns}``.

    Each robot's return is the mean over its episodes; a cell is the mean over robots with a 95%
    bootstrap interval over robots (robots, not episodes, carry the variance of a morphology-agnostic
    controller), and the number of robots x episodes per robot.
    """
    per_robot = robot_means(rows)
    groups = {key: list(robots.values()) for key, robots in per_robot.items()}
    episodes = _episodes_per_robot(rows)
    # the out-of-distribution robots get a column only when the run evaluated some
    splits = [split for split in SPLITS if split != "ood" or any(key[2] == "ood" for key in groups)]
    header = {
        "train": "train robots: mean return [95% CI] (robots x episodes)",
        "novel": "novel robots: mean return [95% CI]",
        "ood": "out-of-distribution robots: mean return [95% CI]",
    }
    lines = [
        "| model | task | " + " | ".join(header[split] for split in splits) + " |",
        "|---|---|" + "---|" * len(splits),
    ]
    for model, task in sorted({(m, t) for m, t, _ in groups}, key=lambda mt: (mt[1], mt[0])):
        cells = []
        for split in splits:
            values = np.asarray(groups.get((model, task, split), []))
            if values.size:
                lo, hi = robot_interval(values)
                cells.append(f"{values.mean():.1f} [{lo:.1f}, {hi:.1f}] ({values.size} x {episodes[(model, task, split)]})")
            else:
                cells.append("–")
        lines.append(f"| {model} | {task} | " + " | ".join(cells) + " |")
    return lines, groups


def robot_means(rows: list[dict[str, str]]) -> dict[tuple[str, str, str], dict[str, float]]:
    """``{(model, task, split): {robot: mean return over its episodes}}`` of ``evaluate/returns.csv`` rows."""
    returns: dict[tuple[str, str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        returns[(row["model"], row["task"], row["split"])][row["morphology"]].append(float(row["return"]))
    return {key: {robot: float(np.mean(values)) for robot, values in robots.items()} for key, robots in returns.items()}


def zero_shot_comparison(profile: Profile, rows: list[dict[str, str]], draws: int = BOOTSTRAP, split: str = "novel") -> list[str]:
    """The paper's zero-shot claim, per training task: does the DivMorph student keep more of its return
    on the novel robots than the HyperDistill student? *Kept* is the mean over novel robots / the mean
    over training robots; the interval resamples the training and the novel robots independently, with
    the same draws for both models (both ran on the same robots), so the difference is paired.

    :param split: the held-out robots: ``novel`` (the paper's comparison) or ``ood`` (the profile's
        out-of-distribution set, reported apart)."""
    per_robot = robot_means(rows)
    models = ("student", "hyperdistill")
    if not any(key[0] == "hyperdistill" for key in per_robot):
        return []
    words = {"novel": f"novel robots (`{profile.novel_set}`)", "ood": f"out-of-distribution robots (`{profile.ood_set}`)"}[split]
    lines = [
        f"## Zero-shot to {words}: the DivMorph student against HyperDistill",
        "",
        f"*Kept*: mean return on the {words} / mean on the training robots (each robot's return the mean of its "
        "episodes); 95% bootstrap intervals resampling training and held-out robots independently, the same draws for "
        "both models (a paired difference). The paper's claim holds on a task when the difference's interval is above 0.",
        "",
        "| task (training / held-out robots) | DivMorph student: held-out / train, kept [95% CI] | HyperDistill: held-out / train, kept [95% CI] | difference in kept [95% CI] | absolute held-out return, student - HyperDistill [95% CI] |",
        "|---|---|---|---|---|",
    ]
    rng = np.random.default_rng(0)
    found = False
    for task in profile.teachers.tasks:
        splits = {(m, s): per_robot.get((m, task, s), {}) for m in models for s in ("train", split)}
        robots = {s: sorted(set(splits[("student", s)]) & set(splits[("hyperdistill", s)])) for s in ("train", split)}
        if not robots["train"] or not robots[split]:
            continue
        found = True
        values = {(m, s): np.array([splits[(m, s)][r] for r in robots[s]]) for m in models for s in ("train", split)}
        picks = {s: rng.integers(0, len(robots[s]), size=(draws, len(robots[s]))) for s in ("train", split)}
        kept, novel = {}, {}
        for m in models:
            train_means, novel_means = values[(m, "train")][picks["train"]].mean(1), values[(m, split)][picks[split]].mean(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                kept[m] = novel_means / train_means
            novel[m] = novel_means
        means = {key: float(v.mean()) for key, v in values.items()}
        points = {m: means[(m, split)] / means[(m, "train")] for m in models}
        cells = [f"{task} ({len(robots['train'])} / {len(robots[split])} robots)"]
        for m in models:
            lo, hi = interval(kept[m])
            cells.append(f"{means[(m, split)]:.1f} / {means[(m, 'train')]:.1f}, {points[m]:.2f} [{lo:.2f}, {hi:.2f}]")
        lo, hi = interval(kept["student"] - kept["hyperdistill"])
        a_lo, a_hi = interval(novel["student"] - novel["hyperdistill"])
        cells += [
            f"{points['student'] - points['hyperdistill']:+.2f} [{lo:+.2f}, {hi:+.2f}]",
            f"{means[('student', split)] - means[('hyperdistill', split)]:+.1f} [{a_lo:+.1f}, {a_hi:+.1f}]",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines if found else []


#: What the student must keep of its teacher's return, and a deployed actor of the student's.
STUDENT_SHARE, DEPLOYED_SHARE = 0.9, 0.95


def student_shares(profile: Profile, rows: list[dict[str, str]], draws: int = BOOTSTRAP) -> list[str]:
    """Each distilled student's return as a share of its teacher's on the training robots, per task, with
    a paired 95% bootstrap interval (the same robots drawn for both); the verdict on the paper's bar
    (>= 90% of the teacher) is *yes* when the interval is above it, *no* when below, else *unclear*.
    The untrained teacher is the floor the shares are read against (a share of a return near 0 means
    little: the table gives both returns)."""
    per_robot = robot_means(rows)
    students = [
        m for m in ("student", *(f"student-{n}" for n in STUDENTS if n != "divmorph"), "hyperdistill") if any(k[0] == m for k in per_robot)
    ]
    if not students or not any(k[0] == "teacher" for k in per_robot):
        return []
    lines = [
        "## Students against their teachers (training robots)",
        "",
        f"Share of the teacher's mean return [paired 95% bootstrap interval over robots]; verdict on >= {STUDENT_SHARE:.0%}: "
        "*yes* when the whole interval is above it, *no* when below, *unclear* when it straddles. In brackets after the "
        "task: the teacher's and its untrained policy's mean returns.",
        "",
        "| task (teacher / untrained) | " + " | ".join(students) + " |",
        "|---|" + "---|" * len(students),
    ]
    rng = np.random.default_rng(0)
    for task in profile.teachers.tasks:
        teacher = per_robot.get(("teacher", task, "train"), {})
        if not teacher:
            continue
        untrained = per_robot.get(("teacher-untrained", task, "train"), {})
        floor = f"{np.mean(list(untrained.values())):.1f}" if untrained else "–"
        cells = [f"{task} ({np.mean(list(teacher.values())):.1f} / {floor})"]
        for model in students:
            student = per_robot.get((model, task, "train"), {})
            robots = sorted(set(teacher) & set(student))
            if not robots:
                cells.append("–")
                continue
            t, v = np.array([teacher[r] for r in robots]), np.array([student[r] for r in robots])
            picks = rng.integers(0, len(robots), size=(draws, len(robots)))
            if (t[picks].mean(1) <= 0).any():  # a share of a return at or below 0 is no share
                cells.append(f"{v.mean():.1f}: n/a (teacher's mean return not above 0)")
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                shares = v[picks].mean(1) / t[picks].mean(1)
            lo, hi = interval(shares)
            verdict = "yes" if lo >= STUDENT_SHARE else "no" if hi < STUDENT_SHARE else "unclear"
            cells.append(f"{v.mean():.1f}: {v.mean() / t.mean():.0%} [{lo:.0%}, {hi:.0%}] {verdict}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _episodes_per_robot(rows: list[dict[str, str]]) -> dict[tuple[str, str, str], int]:
    """Episodes per robot of each (model, task, split) (the most any robot has)."""
    counts: dict[tuple[str, str, str], dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for row in rows:
        counts[(row["model"], row["task"], row["split"])][row["morphology"]] += 1
    return {key: max(robots.values()) for key, robots in counts.items()}


def plot_returns(groups: dict[tuple[str, str, str], list[float]], target: Path, title: str = "") -> None:
    """Deterministic returns per model, one panel per task (tasks' returns differ in scale); bars are
    the mean over robots, error bars their standard deviation."""
    tasks = sorted({t for _, t, _ in groups})
    columns = min(len(tasks), 4)
    rows = (len(tasks) + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.8 * rows), squeeze=False)
    for ax, task in zip(axes.flat, tasks):
        models = sorted({m for m, t, _ in groups if t == task})
        x = np.arange(len(models))
        splits = [split for split in SPLITS if any((m, task, split) in groups for m in models)]
        width = 0.8 / max(len(splits), 1)
        for i, split in enumerate(splits):
            means = [np.mean(groups.get((m, task, split), [np.nan])) for m in models]
            sds = [np.std(groups.get((m, task, split), [np.nan])) for m in models]
            offset = (i - (len(splits) - 1) / 2) * width
            ax.bar(x + offset, means, width, yerr=sds, label=SPLIT_WORDS[split], capsize=2)
        ax.set_xticks(x, models, rotation=45, ha="right", fontsize=7)
        ax.set_title(task, fontsize=9)
        ax.set_ylabel("episode return (deterministic)")
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(tasks) :]:
        ax.axis("off")
    fig.suptitle(title or "returns per model: mean over robots, error bars = sd over robots", fontsize=10)
    fig.tight_layout()
    save_png(fig, target)


def _mean(groups: dict[tuple[str, str, str], list[float]], key: tuple[str, str, str]) -> float:
    values = groups.get(key)
    return float(np.mean(values)) if values else float("nan")


def _percent(part: float, whole: float) -> str:
    return f"{100 * part / whole:.0f}%" if np.isfinite(part) and np.isfinite(whole) and whole > 0 else "n/a"


def findings(profile: Profile, groups: dict[tuple[str, str, str], list[float]], exports: list[dict]) -> list[str]:
    """The run's answers, from the evaluation (mean over robots of deterministic returns) and the exports:
    teachers against the same policy before training, the student against its teachers, zero-shot on
    the novel robots, and the deployed actors' sizes against the return they keep."""
    hyperdistill = any(model == "hyperdistill" for model, _, _ in groups)
    lines = [
        "## Findings",
        "",
        "Means over robots of deterministic returns (`evaluate/returns.csv`); *untrained*: the teacher's run "
        "before its first update (same seed, same initial weights).",
        "",
        "| task | untrained | teacher | DivMorph student (% of teacher; interval and verdict: next section) | dense MetaMorph⚗ student "
        + ("| HyperDistill student " if hyperdistill else "")
        + "| zero-shot novel robots: teacher / student"
        + (" / HyperDistill |" if hyperdistill else " |"),
        "|---|---|---|---|---|---|" + ("---|" if hyperdistill else ""),
    ]
    for task in profile.teachers.tasks:
        untrained, teacher = _mean(groups, ("teacher-untrained", task, "train")), _mean(groups, ("teacher", task, "train"))
        student, dense = _mean(groups, ("student", task, "train")), _mean(groups, ("student-distilled", task, "train"))
        # a point estimate only: the verdict on the paper's bar needs the paired interval (student_shares)
        share = _percent(student, teacher)
        zero_shot = [
            _mean(groups, (model, task, "novel")) for model in ("teacher", "student", *(("hyperdistill",) if hyperdistill else ()))
        ]
        lines.append(
            f"| {task} | {untrained:.1f} | {teacher:.1f} | {student:.1f} ({share}) | {dense:.1f} "
            + (f"| {_mean(groups, ('hyperdistill', task, 'train')):.1f} " if hyperdistill else "")
            + "| "
            + " / ".join(f"{value:.1f}" for value in zero_shot)
            + " |"
        )
    reductions: dict[tuple[str, str], list[float]] = defaultdict(list)
    for r in exports:
        reductions[(r.get("student", "divmorph"), r["task"])].append(r["reduction_vs_metamorph"])
    students = list(dict.fromkeys(name for name, _ in reductions))
    if not students:
        return lines
    lines += [
        "",
        f"Deployment: like-for-like size reduction of each student's compact actor (mean over exported robots) and the "
        f"return its student keeps of the DivMorph student's on the training robots (the compact actor computes the "
        f"student's actions to within 1e-5 x the largest action mean; `return compact / student` below plays one episode "
        f"of each per robot: equal until contacts amplify the last digits). Best: the "
        f"largest reduction keeping >= {DEPLOYED_SHARE:.0%}.",
        "",
        f"| task | {' | '.join(students)} | best (>= {DEPLOYED_SHARE:.0%} of the student's return) |",
        "|---|" + "---|" * (len(students) + 1),
    ]
    reference_label = {name: "student" if name == "divmorph" else f"student-{name}" for name in students}
    for task in profile.teachers.tasks:
        base = _mean(groups, ("student", task, "train"))
        cells, best = [], None
        for name in students:
            if (name, task) not in reductions:
                cells.append("–")
                continue
            reduction = float(np.mean(reductions[(name, task)]))
            kept = _mean(groups, (reference_label[name], task, "train"))
            cells.append(f"{reduction:.1f}x, {_percent(kept, base)}")
            if np.isfinite(kept) and base > 0 and kept >= DEPLOYED_SHARE * base and (best is None or reduction > best[1]):
                best = (name, reduction)
        lines.append(f"| {task} | {' | '.join(cells)} | {f'{best[0]} ({best[1]:.1f}x)' if best else 'none'} |")
    return lines


def _fmt_steps(progress: dict[str, np.ndarray]) -> str:
    steps = progress.get("time/total_timesteps")
    return str(int(np.nanmax(steps))) if steps is not None and len(steps) else "?"


def training_seconds(folder: Path) -> float | None:
    """Wall time a training run spent learning: the last ``time/time_elapsed`` of each attempt
    (``logs/run-*``; a resumed run restarts SB3's clock), summed. ``None`` without logs."""
    total, found = 0.0, False
    for log in log_files(Path(folder), "logs/run-*/progress.csv"):
        elapsed = [float(row["time/time_elapsed"]) for row in read_csv_rows(log) if row.get("time/time_elapsed")]
        if elapsed:
            total, found = total + max(elapsed), True
    return total if found else None


def _stage_row(label: str, run: Path, output: str) -> str:
    seconds = training_seconds(run)
    return f"| {label} | `{output}` | {_fmt_steps(read_progress(run))} | {'?' if seconds is None else f'{seconds:,.0f}'} |"


def _run_record_lines(out: Path) -> list[str]:
    """The machine and the commands of the run, from its ``run.json``."""
    path = out / RECORD
    if not path.is_file():
        return []
    record = json.loads(path.read_text())
    commands = list(dict.fromkeys(entry["command"] for entry in record.get("history", [])))
    versions = ", ".join(f"{k} {v}" for k, v in record.get("versions", {}).items() if v)
    return [
        f"- run record (`{RECORD}`): machine {record.get('machine')}, device used `{record.get('device_used')}`, "
        f"commit `{record.get('git_commit')}`, {versions}",
        "- commands run in this folder, in order (`run.json` history):",
        "",
        "```bash",
        *commands,
        "```",
    ]


def report(profile: Profile, out: Path, command: str = "") -> str:
    """Write the report of run folder ``out`` and return the markdown summary.

    :raises FileNotFoundError: no stage of the run has finished (a summary of models that do not
        exist would mislead).
    """
    out = Path(out)
    if not any(path.is_file() and SUPERSEDED not in path.relative_to(out).parts for path in out.glob("**/done.json")):
        raise FileNotFoundError(f"nothing to report in {out}: no stage has finished there (no done.json); run the stages first")
    folder = out / "report"
    folder.mkdir(parents=True, exist_ok=True)
    lines = [
        f"# DivMorph pipeline — profile `{profile.name}`",
        "",
        f"- command: `{command or 'divmorph pipeline --profile ' + profile.name}`",
        f"- written {time.strftime('%Y-%m-%d %H:%M')} on {platform.node() or 'this machine'} "
        f"({platform.processor() or platform.machine()}), seed {profile.seed}, device {profile.device}",
        f"- robots: {_robots_sentence(profile)}; episodes of at most {profile.max_episode_steps} steps",
        f"- transfer: tasks {profile.transfer.tasks}, arms {profile.transfer.arm_list()}, seeds {profile.transfer.seeds}, "
        f"{profile.transfer.n_timesteps} env steps per run; teachers {profile.teachers.n_timesteps}, "
        f"distillation {profile.distill.n_timesteps} env steps",
        "",
        *_run_record_lines(out),
        "",
        "## Stages",
        "",
        "| stage | output | env steps | training wall time (s) |",
        "|---|---|---|---|",
    ]
    for task in profile.teachers.tasks:
        lines.append(_stage_row(f"teacher {task} (MetaMorph, PPO)", out / "teachers" / task, f"teachers/{task}/model.zip"))
    lines.append(_stage_row("DAgger distillation (DivMorph student)", out / "student", "student/model.zip"))
    for name in STUDENTS:
        if name != "divmorph" and (out / "students" / name / "done.json").is_file():
            lines.append(
                _stage_row(f"DAgger distillation ({STUDENTS[name].description})", out / "students" / name, f"students/{name}/model.zip")
            )
    if (out / "grl" / "done.json").is_file():
        learngene = json.loads((out / "grl" / "learngene.json").read_text())
        lines.append(
            f"| GRL evolution ({profile.grl.generations} generations x {profile.grl.population} agents x "
            f"{profile.grl.steps_per_agent} steps); learngene {'+'.join(learngene['units'])} | `grl/learngene.json` | "
            f"{profile.grl.generations * profile.grl.population * profile.grl.steps_per_agent} | ? |"
        )
    for task in transfer_tasks(profile, out):
        for arm in ARMS:
            for seed in transfer_seeds(profile, out, task, arm):
                run = transfer_folder(out, task, arm, seed)
                if (run / "done.json").is_file():
                    lines.append(_stage_row(f"transfer {task} ({arm}, seed {seed})", run, f"{run.relative_to(out)}/model.zip"))

    plot_curves(profile, out, folder / "curves.png")
    lines += ["", "## Learning curves", "", "![curves](report/curves.png)", ""]
    metrics = [m for task in transfer_tasks(profile, out) for m in write_metrics(profile, out, task)]
    if metrics:
        closest = [json.loads(p.read_text()) for p in sorted((out / "transfer").glob("*/closest-by-*.json"))]
        lines += [
            "## Transfer metrics",
            "",
            f"Deterministic evaluations every {profile.transfer.eval_every} env steps on "
            f"{len(transfer_eval_robots(profile, 'train'))} training and {len(transfer_eval_robots(profile, 'novel'))} novel robots "
            f"(spread over each set; {profile.transfer.eval_episodes} episode(s) per robot); mean over seeds and robots [95% bootstrap interval, "
            "seeds and robots resampled]. AUC: area under the curve / steps (the mean return over training). Level: "
            f"{EFFICIENCY_FRACTION:.0%} of the way from scratch's zero-shot return to the best arm's final return; steps to "
            "hold the level: the env step from which the arm's mean curve stays at or above it to the end (not held: its last "
            "evaluation is below; >budget: some bootstrap draws never hold it). Speed-up vs scratch: scratch's steps / the "
            "arm's, only where both hold the level (>=: scratch never does, a lower bound).",
            "",
            *metrics_table(metrics),
            "",
        ]
        lines += [
            f"- closest training task to {c['task']} by {c['criterion']}: {c['closest']} "
            f"({', '.join(f'{t} {v:.3f}' for t, v in c['scores'].items())})"
            for c in closest
        ]
    figures = make_figures(profile, out)
    if figures:
        lines += [
            "",
            "## Figures",
            "",
            *[
                f"- {name}: `{path.relative_to(out)}` (numbers: `{path.with_suffix('.csv').relative_to(out)}`): {CAPTIONS[name]}"
                for name, path in figures.items()
            ],
            "",
        ]

    returns_file = out / "evaluate" / "returns.csv"
    if log_file(returns_file) is not None:
        rows = read_returns(returns_file)
        table, groups = returns_table(rows)
        episodes = profile.evaluate.episodes
        plot_returns(
            groups,
            folder / "returns.png",
            f"profile {profile.name}, seed {profile.seed}: deterministic return, mean over robots "
            f"({_robots_phrase(profile)} / novel robots), {episodes} episode(s) each; error bars = sd over robots",
        )
        lines += [
            "",
            "## Per-morphology evaluation (deterministic actions)",
            "",
            *table,
            "",
            f"Mean over robots of each robot's mean return over its deterministic episodes ({episodes} per robot), with a "
            "95% bootstrap interval over robots; the error bars of the figure are the sd over robots. Per-robot rows: "
            "`evaluate/returns.csv`.",
            "",
            "![returns](report/returns.png)",
            "",
            *findings(profile, groups, [json.loads(p.read_text()) for p in export_reports(out)]),
            "",
            *student_shares(profile, rows),
            "",
            *zero_shot_comparison(profile, rows),
            "",
            *zero_shot_comparison(profile, rows, split="ood"),
        ]
    gates_file = out / "evaluate" / "gates.npz"
    if gates_file.is_file():
        with np.load(gates_file) as data:
            gates = {k: data[k] for k in data.files}
        used = (gates["task_gates"] > 0).sum(0)
        lines += [
            "",
            "## Gates",
            "",
            f"![gates]({figures['gates'].relative_to(out)})",  # make_figures wrote it from the same gates.npz
            "",
            f"Task tailors selected by at least one of the 10 instructions: {int((used > 0).sum())} of {len(used)}; "
            f"distinct task-tailor selections: {distinct_selections(gates['task_gates'])} among {len(gates['tasks'])} tasks; "
            f"distinct morphology-tailor selections: {distinct_selections(gates['morphology_gates'])} among "
            f"{len(gates['robots'])} robots (the correlation of two gate vectors that select the same top-k "
            "tailors is close to 1 even when their weights differ).",
        ]

    exports = [json.loads(path.read_text()) for path in export_reports(out)]
    if exports:
        lines += [
            "",
            "## Deployment: pruned compact actors",
            "",
            "| student | robot | task | exported from | MetaMorph actor (folded) | compact DivMorph | reduction (like for like) "
            "| MetaMorph actor (unfolded) | folding alone | max abs diff | latency compact / student (ms, batch 1) "
            "| return compact / student (1 episode) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in exports:
            returns = f"{r['compact_return']:.1f} / {r['student_return']:.1f}" if "compact_return" in r else "–"
            lines.append(
                f"| {r.get('student', 'divmorph')} | {r['robot']} | {r['task']} | {r['source_label']} | {r['metamorph_folded_weights']:,} | "
                f"{r['compact_weights']:,} | {r['reduction_vs_metamorph']:.1f}x | {r['metamorph_actor_parameters']:,} | "
                f"{r['folding_metamorph']:.2f}x | {r['max_abs_diff']:.1e} | {r['latency_compact_ms']:.3f} / {r['latency_student_ms']:.3f} "
                f"({r['speedup_vs_student']:.1f}x) | {returns} |"
            )
        lines += [
            "",
            "Like for like: the MetaMorph actor of the same task and sizes is exported through the same folding "
            "(context rows, position embedding, padded tokens and encoders of observations the task lacks become "
            "constants), so the reduction counts pruning only; 'folding alone' is what folding saves MetaMorph. "
            "Baked normalisation statistics are not counted (both actors need them).",
        ]
    summary = "\n".join(lines) + "\n"
    atomic_write_text(out / "summary.md", summary)
    return summary


def _robots_sentence(profile: Profile) -> str:
    """Which robots train and which are novel, as a reader can check them: novel robots drawn from
    the training set are the ones after the training robots (robots 11-20, not "the first 10")."""

    def count(n: int | None) -> str:
        return "all" if n is None else str(n)

    train = f"training: the first {count(profile.train_robots)} of `{profile.train_set}`"
    if profile.novel_set == profile.train_set:
        start = (profile.train_robots or 0) + 1
        span = f"{start}-{start + profile.novel_robots - 1}" if profile.novel_robots else f"{start} onward"
        sentence = f"{train}; novel: robots {span} of `{profile.novel_set}` (the ones after the training robots)"
    else:
        sentence = f"{train}; novel: the first {count(profile.novel_robots)} of `{profile.novel_set}` (never a training robot)"
    if profile.ood_set is not None:
        sentence += f"; out of distribution (reported apart): the first {count(profile.ood_robots)} of `{profile.ood_set}`"
    return sentence
