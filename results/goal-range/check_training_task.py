"""Does bounding the goal input keep what the trained models do on Patrol, the one training task with a goal? (issue 67 (b))

``goal_range=R`` observes a goal farther than R metres at R in its own direction. Patrol's goals lie
about 10 m away, so R = 10 should change nearly nothing there; this checks it before any transfer run
uses the option. Each model (the Patrol teacher, the DivMorph student and the dense distilled
student, both told Patrol's instruction) is evaluated on the race's 20 curve robots with raw and
bounded goals under the same evaluation seeds (3 deterministic episodes per robot and seed; the same
reset noise in both conditions), and the per-robot difference is bootstrapped over robots.

    python results/goal-range/check_training_task.py --run results/cpu100 --range 10 --eval-seeds 0 1
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
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import transfer_eval_robots
from divmorph.pretrained import load_pretrained

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, default=Path("results/cpu100"))
    parser.add_argument("--task", default="Patrol")
    parser.add_argument("--range", type=float, default=10.0, help="goal_range (m)")
    parser.add_argument("--eval-seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--out", type=Path, default=HERE / "training-task.csv.gz")
    args = parser.parse_args()
    th.set_num_threads(1)
    profile = recorded_profile(args.run / "run.json")
    robots = transfer_eval_robots(profile, "train")
    models = {
        f"teacher-{args.task}": teacher_folder(args.run, args.task),
        "divmorph": student_folder(args.run, "divmorph"),
        "distilled": student_folder(args.run, "distilled"),
    }
    rows = []
    for label, folder in models.items():
        model = load_pretrained(folder)
        for goal_range in (None, args.range):
            for seed in args.eval_seeds:
                start = time.time()
                settings = {} if goal_range is None else {"goal_range": goal_range}
                found = model.evaluate(
                    robots, task=args.task, episodes=3, seed=seed, max_episode_steps=profile.max_episode_steps, **settings
                )
                frame = pd.DataFrame(found).assign(model=label, goal_range=goal_range or 0.0, eval_seed=seed)
                rows.append(frame)
                print(
                    f"{label} goal_range={goal_range} seed {seed}: {frame['return'].mean():.1f} ({time.time() - start:.0f} s)", flush=True
                )
    table = pd.concat(rows, ignore_index=True)
    # kept per robot and evaluation seed (the mean of its 3 episodes): what the paired reading uses
    table.groupby(["model", "goal_range", "eval_seed", "robot"], as_index=False)["return"].mean().to_csv(
        args.out, index=False, float_format="%.5g"
    )
    lines = [
        f"| model ({args.task}) | raw goal | goal_range {args.range:g} | bounded minus raw [95% CI over robots] |",
        "|---|---:|---:|---|",
    ]
    for label, part in table.groupby("model", sort=False):
        per = part.groupby(["goal_range", "robot"])["return"].mean().unstack("goal_range")
        diff = (per[args.range] - per[0.0]).to_numpy()
        lo, hi = robot_interval(diff)
        lines.append(f"| {label} | {per[0.0].mean():.1f} | {per[args.range].mean():.1f} | {diff.mean():+.1f} [{lo:+.1f}, {hi:+.1f}] |")
    lines.append(
        f"\n{len(robots)} curve robots x {len(args.eval_seeds)} evaluation seeds x 3 deterministic episodes per condition; "
        f"{time.strftime('%Y-%m-%d')}, {platform.node()}, 1 torch thread."
    )
    text = "\n".join(lines)
    (args.out.parent / "training-task.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
