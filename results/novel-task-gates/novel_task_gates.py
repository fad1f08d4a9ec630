"""Which task tailors should a DivMorph student start a novel task with? Its zero-shot return under each instruction (issue 42).

On a novel task the DivMorph student's task gates come from the novel instruction's embedding
through a gate network trained on five instructions only; the transfer arm then fine-tunes the
tailors those gates select, with the gates fixed. In ``results/cpu100``'s race the student started
PointNav at 10 while the dense student started at 145 and the fine-tuned Patrol teacher at 112, and
it never caught up. This study asks whether the start is a matter of which tailors are selected:
it evaluates the student on each novel task with the env's instruction replaced by each training
task's (the gates and every other reader of the task embedding then see that task), beside its own
instruction, the dense student and the ``closest`` teacher (MetaMorph→'s start), all through the
same :meth:`~divmorph.pretrained.SavedModel.evaluate` on the race's curve robots (training
split), several evaluation seeds x 3 deterministic episodes per robot.

Rows go to ``<out>/returns.csv.gz`` (one per episode; conditions already there are skipped, so the
study resumes); ``--report`` writes ``<out>/README.md``'s tables.

    python results/novel-task-gates/novel_task_gates.py --run results/cpu100 --out results/novel-task-gates --tasks PointNav
    python results/novel-task-gates/novel_task_gates.py --run results/cpu100 --out results/novel-task-gates --report

The ablated students (distilled in a branch of the run, ``divmorph distill --students no-kdiv-transformer``)
join the same rows, each told its own task and the closest training task's (their race starts)::

    python results/novel-task-gates/novel_task_gates.py --run runs/ablate-no-kdiv-transformer --out results/novel-task-gates --students no-kdiv-transformer
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import pandas as pd
import torch as th

from divmorph.pipeline.folders import student_folder, teacher_folder
from divmorph.pipeline.metrics import robot_interval
from divmorph.pipeline.config import Profile
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import transfer_eval_robots
from divmorph.pipeline.transfer import closest_task
from divmorph.pretrained import load_pretrained
from unimal_envs.instructions import INSTRUCTIONS

ROWS = "returns.csv.gz"


def conditions(run: Path, profile: Profile, task: str, students: list[str] | None = None) -> list[tuple[str, Path, str]]:
    """``(model label, folder, instruction of)`` for one novel task: the DivMorph student under every
    instruction, the dense student and MetaMorph→'s start; with ``students``, only those students
    (e.g. the ablations, distilled in a branch of the run), each told its own task and the closest's."""
    closest = closest_task(profile, run, task, by="embedding")["closest"]
    if students:
        return [(name, student_folder(run, name), told) for name in students for told in dict.fromkeys((task, closest))]
    found = [("divmorph", student_folder(run, "divmorph"), task)]
    found += [("divmorph", student_folder(run, "divmorph"), other) for other in profile.teachers.tasks]
    found += [("distilled", student_folder(run, "distilled"), task), ("distilled", student_folder(run, "distilled"), closest)]
    found += [(f"teacher-{closest}", teacher_folder(run, closest), task)]
    return found


def measure(args: argparse.Namespace) -> None:
    profile = recorded_profile(args.run / "run.json")
    robots = transfer_eval_robots(profile, "train")
    path = args.out / ROWS
    args.out.mkdir(parents=True, exist_ok=True)
    table = pd.read_csv(path) if path.is_file() else pd.DataFrame(columns=["task", "model", "instruction_of", "eval_seed"])
    done = set(map(tuple, table[["task", "model", "instruction_of", "eval_seed"]].astype(str).to_numpy()))
    for task in args.tasks:
        for label, folder, instruction_of in conditions(args.run, profile, task, args.students):
            model = load_pretrained(folder)
            for seed in args.eval_seeds:
                if (task, label, instruction_of, str(seed)) in done:
                    continue
                start = time.time()
                rows = model.evaluate(
                    robots,
                    task=task,
                    episodes=args.episodes,
                    seed=seed,
                    max_episode_steps=profile.max_episode_steps,
                    instruction=INSTRUCTIONS[instruction_of],
                )
                frame = pd.DataFrame(rows).assign(task=task, model=label, instruction_of=instruction_of, eval_seed=seed)
                table = pd.concat([table, frame], ignore_index=True)
                table.to_csv(path.with_suffix(".tmp.gz"), index=False)
                path.with_suffix(".tmp.gz").replace(path)
                print(
                    f"[novel-task-gates] {task} {label} told {instruction_of} eval seed {seed}: "
                    f"{frame['return'].mean():.1f} ({time.time() - start:.0f} s)",
                    flush=True,
                )


def report(args: argparse.Namespace) -> str:
    table = pd.read_csv(args.out / ROWS)
    lines = []
    for task, rows in table.groupby("task", sort=False):
        own = rows[(rows.model == "divmorph") & (rows.instruction_of == task)].groupby("robot")["return"].mean()
        lines += [
            f"### {task}",
            "",
            "| model | told it is doing | episodes | mean return [95% CI over robots] | minus the DivMorph student told its own task [paired 95% CI] |",
            "|---|---|---:|---|---|",
        ]
        for (model, told), part in rows.groupby(["model", "instruction_of"], sort=False):
            per_robot = part.groupby("robot")["return"].mean()
            low, high = robot_interval(per_robot.to_numpy())
            paired = (per_robot - own.reindex(per_robot.index)).dropna().to_numpy()
            dlow, dhigh = robot_interval(paired)
            lines.append(
                f"| {model} | {told}{' (its own)' if told == task else ''} | {len(part)} | {per_robot.mean():.1f} [{low:.1f}, {high:.1f}] "
                f"| {paired.mean():+.1f} [{dlow:+.1f}, {dhigh:+.1f}] |"
            )
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", type=Path, default=Path("results/cpu100"))
    parser.add_argument("--out", type=Path, default=Path("results/novel-task-gates"))
    parser.add_argument("--tasks", nargs="+", default=["PointNav", "Escape", "Exploration"])
    parser.add_argument("--eval-seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument(
        "--students",
        nargs="+",
        default=None,
        help="only these students of --run (e.g. no-kdiv-transformer), each told its own task and the closest training task's",
    )
    parser.add_argument("--report", action="store_true", help="print the tables from the rows recorded so far")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.report:
        print(report(args))
        return
    start = time.time()
    measure(args)
    print(f"[novel-task-gates] done in {time.time() - start:.0f} s on {platform.node()}", flush=True)


if __name__ == "__main__":
    main()
