"""Which robots does each shipped model do well on? The showcase list of a recorded run (issue 46).

A video of a model should show what it learnt, on a robot it does well on, and say that the robot
was chosen: this study reads the run's evaluation (``evaluate/returns.csv``: 3 deterministic
episodes per robot) and lists, per model and training task, the training robots with the highest
mean return -- chosen on the *training* robots, never on the held-out ones (a showcase picked on the
test set would be a choice made on it) -- beside the model's mean over all its training robots, and
the command that films the best one (``divmorph record FOLDER --robot best`` picks the same robot).

    python results/cpu100/best_robots.py --run results/cpu100            # writes results/cpu100/best-robots.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

from divmorph.pipeline.files import log_file, read_csv_rows
from divmorph.pretrained import robot_means

TRAINING_TASKS = ("FT", "VT", "Incline", "Obstacle", "Patrol")

#: model label in ``evaluate/returns.csv`` -> its shipped folder (relative to the run) and what it is
SHIPPED = {
    "teacher": ("teachers/{task}", "MetaMorph teacher"),
    "student": ("student", "DivMorph student"),
    "student-distilled": ("students/distilled", "dense MetaMorph⚗ student"),
    "student-deploy-g1k1": ("students/deploy-g1k1", "deployment student (width 64)"),
}


def best_robots(returns: list[dict[str, str]], model: str, task: str, n: int) -> tuple[list[tuple[str, float]], float]:
    """The ``n`` training robots with the highest mean return of ``model`` on ``task``, and its mean over all."""
    means = robot_means(returns, model, task, "train")
    return means[:n], sum(value for _, value in means) / max(len(means), 1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, default=Path("results/cpu100"), help="a run folder with evaluate/returns.csv")
    parser.add_argument("--top", type=int, default=5, help="robots listed per model and task")
    args = parser.parse_args(argv)
    path = log_file(args.run / "evaluate" / "returns.csv")
    if path is None:
        raise SystemExit(f"{args.run} has no evaluate/returns.csv; run `divmorph evaluate --run {args.run}` first")
    returns = read_csv_rows(path)
    lines = [
        f"# Robots each shipped model does well on: `{args.run}`",
        "",
        "Made by `python results/cpu100/best_robots.py --run " + str(args.run) + "` from the run's evaluation "
        "(`evaluate/returns.csv`, 3 deterministic episodes per robot): per model and training task, the "
        f"{args.top} training robots with the highest mean return, chosen on the training robots only. "
        "The mean over all training robots is beside them: these are the model's best, not its typical robots. "
        "`divmorph record FOLDER --robot best` films the first of each list (FOLDER as in the table; a "
        "student also needs `--task`); `load_pretrained(FOLDER).best_robots(task)` returns the list.",
        "",
        "| model | task | mean over the training robots | best training robots (mean return) | film the best |",
        "|---|---|---:|---|---|",
    ]
    for model, (folder, name) in SHIPPED.items():
        for task in [t for t in TRAINING_TASKS if t in {row["task"] for row in returns if row["model"] == model}]:
            top, mean = best_robots(returns, model, task, args.top)
            stage = args.run / folder.format(task=task)
            if not top or not (stage / "model.zip").is_file():
                continue
            command = f"`divmorph record {stage} --robot best" + ("" if "{task}" in folder else f" --task {task}") + "`"
            robots = ", ".join(f"`{robot}` ({value:,.0f})" for robot, value in top)
            lines.append(f"| {name} | {task} | {mean:,.0f} | {robots} | {command} |")
    lines.append("")
    (args.run / "best-robots.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
