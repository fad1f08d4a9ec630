"""How far apart are a policy's sampled (training-time) and deterministic returns? A control for training logs.

    python results/gpu-h200/stochastic_gap.py --model cpu100-FT=results/cpu100/teachers/FT \
        --model gpu-FT=/path/to/step-000012134400 --out results/gpu-h200/stochastic-gap.md

PPO logs the return of the episodes it *samples* (actions drawn from the policy's Gaussian), while
the evaluations roll out its mean action. When the two differ a lot -- the paper-size GPU teacher
logged 117 while its deterministic evaluation returned 965 -- either the action noise itself costs
the return, or the training env's episodes differ from the evaluation env's. This script separates
the two: it rolls out each model both ways in the *same* single-robot C envs (the evaluation's
:func:`~divmorph.pipeline.curves.evaluate_model`, seed 0, the same robots and episodes), so a gap
that remains here is the noise's, not the env's.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from divmorph.pipeline.config import load_profile
from divmorph.pipeline.curves import evaluate_model
from divmorph.pipeline.metrics import robot_interval
from divmorph.pipeline.robots import transfer_eval_robots


def robot_means(rows: list[dict]) -> np.ndarray:
    """Mean return per robot (episodes averaged first), in the rows' robot order."""
    robots = list(dict.fromkeys(row["morphology"] for row in rows))
    return np.array([np.mean([r["return"] for r in rows if r["morphology"] == robot]) for robot in robots])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", action="append", required=True, help="LABEL=FOLDER (model.zip + vecnormalize.pkl); repeat")
    parser.add_argument("--task", default="FT")
    parser.add_argument("--episodes", type=int, default=3, help="episodes per robot, each way")
    parser.add_argument("--profile", default="cpu100", help="the profile whose transfer.eval_robots (spread training robots) are used")
    parser.add_argument("--out", type=Path, required=True, help="markdown table")
    args = parser.parse_args()
    torch.set_num_threads(1)
    profile = load_profile(args.profile)
    robots = transfer_eval_robots(profile, "train")
    lines = [
        f"# Sampled against deterministic returns ({args.task}, {len(robots)} training robots x {args.episodes} episodes)",
        "",
        f"`python results/gpu-h200/stochastic_gap.py {' '.join('--model ' + m for m in args.model)} --task {args.task} "
        f"--episodes {args.episodes} --profile {args.profile} --out {args.out}`; the robots: the profile's "
        f"`transfer.eval_robots` spread over its training set; single C envs with the env arguments each model trained with, seed 0, episodes of at most "
        f"{profile.max_episode_steps} steps; {platform.machine()} CPU, one thread. Mean over robots [95% bootstrap CI over robots].",
        "",
        "| model | deterministic (mean action) | sampled (as in training) | sampled - deterministic [paired CI] | episode length: deterministic / sampled | wall time |",
        "|---|---|---|---|---|---:|",
    ]
    for spec in args.model:
        label, folder = spec.split("=", 1)
        start = time.time()
        found = {
            way: evaluate_model(Path(folder), args.task, robots, args.episodes, profile.max_episode_steps, profile.seed, deterministic=way)
            for way in (True, False)
        }
        det, sam = robot_means(found[True]), robot_means(found[False])
        lengths = {way: np.mean([r["length"] for r in rows]) for way, rows in found.items()}
        lo, hi = robot_interval(det)
        slo, shi = robot_interval(sam)
        dlo, dhi = robot_interval(sam - det)
        lines.append(
            f"| {label} | {det.mean():.0f} [{lo:.0f}, {hi:.0f}] | {sam.mean():.0f} [{slo:.0f}, {shi:.0f}] | "
            f"{(sam - det).mean():+.0f} [{dlo:+.0f}, {dhi:+.0f}] | {lengths[True]:.0f} / {lengths[False]:.0f} | {time.time() - start:.0f} s |"
        )
        print(lines[-1], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
