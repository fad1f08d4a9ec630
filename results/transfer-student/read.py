"""The transfer student against cpu100's: what each keeps of the teachers, and how many tailors its router uses.

Both students are distilled from the same cpu100 teachers and evaluated by the same ``divmorph evaluate``
(3 deterministic episodes on each of the 100 official training robots, the run's seed); each share is
the student's mean return over the teacher's on the same robots, with a paired 95% bootstrap interval
over robots (one distillation run each, so robots are what varies here). The router: the task gates the
student computes for each of the ten task instructions (five training, five novel) on one robot, and
the morphology gates over the 100 training robots; a tailor counts as used where its gate weight is
above 0.

    python results/transfer-student/read.py --run RUN --evaluated EVAL [EVAL ...] \
        --comparator-run RUN400 --comparator-evaluated EVAL400      # writes reading.md here

``--comparator-*``: the DivMorph student of cpu100's proportions distilled alike for 400k steps (the ablation
race's comparator), so that the budget is the same on both sides of the proportions' comparison.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from divmorph.pipeline.config import load_profile
from divmorph.pipeline.envs import profile_env_kwargs
from divmorph.pipeline.evaluate import student_gates
from divmorph.pipeline.metrics import BOOTSTRAP, interval
from divmorph.pipeline.report import read_returns, robot_means
from divmorph.pipeline.robots import profile_robots
from unimal_envs.contract import NOVEL_TASKS, TRAIN_TASKS

HERE = Path(__file__).resolve().parent
REFERENCE = HERE.parent / "cpu100"


def share(teacher: dict[str, float], student: dict[str, float], draws: int = BOOTSTRAP) -> tuple[float, float, float]:
    """The student's mean over the teacher's on their common robots, and its paired 95% bootstrap interval."""
    robots = sorted(set(teacher) & set(student))
    t, s = np.array([teacher[r] for r in robots]), np.array([student[r] for r in robots])
    picks = np.random.default_rng(0).integers(0, len(robots), size=(draws, len(robots)))
    lo, hi = interval(s[picks].mean(1) / t[picks].mean(1))
    return s.mean() / t.mean(), lo, hi


def router(gates: dict[str, np.ndarray]) -> list[str]:
    """Markdown lines: each task's selected task tailors (weights), and the distinct tailors per group."""
    tasks = [str(t) for t in gates["tasks"]]
    chosen = {task: np.nonzero(row > 0)[0] for task, row in zip(tasks, gates["task_gates"])}
    lines = ["| task | task tailors selected (weight) |", "|---|---|"]
    for task, row in zip(tasks, gates["task_gates"]):
        picked = ", ".join(f"{i} ({row[i]:.2f})" for i in chosen[task])
        lines.append(f"| {task}{' (novel)' if task in NOVEL_TASKS else ''} | {picked} |")
    n_task = gates["task_gates"].shape[1]
    for group, names in (("training", TRAIN_TASKS), ("novel", NOVEL_TASKS)):
        used = sorted({int(i) for t in names for i in chosen[t]})
        pairs = len({tuple(chosen[t]) for t in names})
        lines.append(
            f"\n{group.capitalize()} tasks: {len(used)} of {n_task} task tailors used ({used}); {pairs} distinct selections of {len(names)} tasks."
        )
    morphology = gates["morphology_gates"]
    used = int((morphology > 0).any(0).sum())
    selections = len({tuple(np.nonzero(row > 0)[0]) for row in morphology})
    lines.append(
        f"Morphology gates over {len(morphology)} training robots: {used} of {morphology.shape[1]} tailors used, {selections} distinct selections."
    )
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="the transfer student's run (a branch of results/cpu100)")
    parser.add_argument("--evaluated", type=Path, nargs="+", required=True, help="its `divmorph evaluate --into` folders")
    parser.add_argument("--comparator-run", type=Path, default=None, help="the 12 + 12 student distilled alike (400k)")
    parser.add_argument("--comparator-evaluated", type=Path, nargs="*", default=[], help="its `divmorph evaluate --into` folders")
    args = parser.parse_args(argv)
    reference = robot_means(read_returns(REFERENCE / "evaluate" / "returns.csv"))
    new = robot_means([row for folder in args.evaluated for row in read_returns(folder / "returns.csv")])
    comparator = robot_means([row for folder in args.comparator_evaluated for row in read_returns(folder / "returns.csv")])
    lines = [
        "# The transfer student: shares of the teachers and its router",
        "",
        "Made by `python results/transfer-student/read.py` (its docstring: how). Share of the cpu100 teacher's mean "
        "return on the 100 training robots [paired 95% bootstrap over robots], 3 deterministic episodes per robot:",
        "",
        "| task | teacher | cpu100 student (12 + 12 tailors, 1M steps) | 12 + 12 tailors, 400k steps | "
        "transfer student (4 + 4 tailors, load balance, 400k steps) |",
        "|---|---:|---|---|---|",
    ]
    for task in TRAIN_TASKS:
        teacher = reference[("teacher", task, "train")]
        cells = [task, f"{np.mean(list(teacher.values())):.0f}"]
        for rows in (reference, comparator, new):
            student = rows.get(("student", task, "train"))
            if not student:
                cells.append("--")
                continue
            mean, lo, hi = share(teacher, student)
            cells.append(f"{np.mean(list(student.values())):.0f}: {mean:.0%} [{lo:.0%}, {hi:.0%}]")
        lines.append("| " + " | ".join(cells) + " |")
    profile = load_profile("cpu100-transfer")
    robots = profile_robots(profile, "train")
    runs = [
        ("cpu100 student", REFERENCE),
        *([("12 + 12 student at 400k", args.comparator_run)] if args.comparator_run else []),
        ("transfer student", args.run),
    ]
    for name, run in runs:
        lines += ["", f"## Router of the {name}", "", *router(student_gates(run, robots, profile.seed, **profile_env_kwargs(profile)))]
    (HERE / "reading.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
