"""Do fine-tuned policies improve the return PPO optimises? Start and final models of transfer runs, sampled actions (issue 42).

PPO maximises the return of the policy it samples from (a Gaussian around the mean action; the
std is fixed at 0.9 in these runs), while the race evaluates the mean action. This evaluates each
variant's starting model and each run's final model with *sampled* actions, on the race's curve
robots (``--eval-seeds`` x 3 episodes per robot, the same episodes for start and finish), and
reports the change per robot, paired.

    python results/transfer-pointnav/transfer_stochastic.py --task PointNav --out results/transfer-pointnav/stochastic.csv.gz \\
        --variant "own gates=/work/race/gates-instruction:divmorph:PointNav"

A variant is ``label=folder:arm:instruction of`` (the folder a ``results/finetune-known-task/finetune_known_task.py``
branch holding ``transfer/<task>/<arm>/seed-*`` and the run's ``source.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd
import torch as th

from divmorph.pipeline.metrics import run_interval
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import transfer_eval_robots
from divmorph.pretrained import load_pretrained
from unimal_envs.instructions import INSTRUCTIONS


def measure(args: argparse.Namespace) -> pd.DataFrame:
    found = pd.read_csv(args.out) if args.out.is_file() else pd.DataFrame(columns=["variant", "model"])
    done = set(zip(found["variant"], found["model"]))
    for item in args.variant:
        label, _, spec = item.partition("=")
        folder, arm, told = spec.split(":")
        folder = Path(folder)
        profile = recorded_profile(folder / "run.json")
        robots = transfer_eval_robots(profile, "train")
        runs = sorted((folder / "transfer" / args.task / arm).glob("seed-*"))
        start = folder / json.loads((runs[0] / "source.json").read_text())["source"]
        for name, model_folder in [("start", start)] + [(run.name, run) for run in runs]:
            if (label, name) in done:
                continue
            model = load_pretrained(model_folder)
            rows = []
            for seed in args.eval_seeds:
                rows += [
                    {**row, "eval_seed": seed}
                    for row in model.evaluate(
                        robots,
                        task=args.task,
                        episodes=3,
                        seed=seed,
                        max_episode_steps=profile.max_episode_steps,
                        deterministic=False,
                        instruction=INSTRUCTIONS[told],
                    )
                ]
            frame = pd.DataFrame(rows).assign(variant=label, model=name)
            found = pd.concat([found, frame], ignore_index=True)
            found.to_csv(args.out, index=False)
            print(f"[transfer-stochastic] {label} {name}: {frame['return'].mean():.1f}", flush=True)
    return found


def report(found: pd.DataFrame) -> str:
    lines = [
        "| variant | start (sampled actions) | final, mean of runs | change, paired per robot and run [95% CI] |",
        "|---|---:|---:|---|",
    ]
    for label, part in found.groupby("variant", sort=False):
        per = part.groupby(["model", "robot"])["return"].mean().unstack("model")
        finals = [c for c in per.columns if c != "start"]
        # runs x robots: the interval resamples the runs and the robots within them (not run x robot pairs)
        change = (per[finals].sub(per["start"], axis=0)).dropna().T.to_numpy()
        low, high = run_interval(change)
        lines.append(
            f"| {label} | {per['start'].mean():.0f} | {per[finals].mean().mean():.0f} ({len(finals)} runs) | {change.mean():+.0f} [{low:+.0f}, {high:+.0f}] |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--out", type=Path, required=True, help="rows (csv.gz); the study resumes from it")
    parser.add_argument("--variant", action="append", default=[], metavar="LABEL=FOLDER:ARM:INSTRUCTION_OF")
    parser.add_argument("--eval-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--report", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(1)
    found = pd.read_csv(args.out) if args.report else measure(args)
    print(report(found))


if __name__ == "__main__":
    main()
