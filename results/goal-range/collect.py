"""Gather the finished runs of the study's run folder (``runs/goal-range-pointnav``, not tracked) into the
small tables ``read.py`` reads: ``curves.csv.gz`` (each run's mean deterministic return per robot at each
evaluation, training and held-out robots), ``training.csv.gz`` (each PPO update's stochastic training return
and approximate KL) and ``starts.csv`` (each arm's many-draw start per robot, with the
goal bounded: the mean over 5 evaluation seeds x 3 episodes).

    python results/goal-range/collect.py --from runs/goal-range-pointnav
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
LOGGED = {"time/total_timesteps": "timesteps", "rollout/ep_rew_mean": "training_return", "train/approx_kl": "approx_kl"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--from", dest="source", type=Path, default=Path("runs/goal-range-pointnav"))
    args = parser.parse_args()
    curves, training = [], []
    for done in sorted((args.source / "transfer").glob("*/*/seed-*/done.json")):
        run = done.parent
        task, arm, seed = run.parent.parent.name, run.parent.name, int(run.name.split("-")[1])
        frame = pd.read_csv(run / "eval.csv").groupby(["timesteps", "split", "robot"], as_index=False)["return"].mean()
        curves.append(frame.assign(task=task, arm=arm, seed=seed))
        log = pd.concat(pd.read_csv(p) for p in sorted((run / "logs").glob("run-*/progress.csv")))
        log = log[list(LOGGED)].rename(columns=LOGGED).dropna(subset=["approx_kl"])
        training.append(log.assign(task=task, arm=arm, seed=seed))
        print(f"{run}: {len(frame)} curve rows, {len(log)} updates")
    pd.concat(curves).to_csv(HERE / "curves.csv.gz", index=False, float_format="%.5g")
    pd.concat(training).to_csv(HERE / "training.csv.gz", index=False, float_format="%.4g")
    saved = json.loads((args.source / "baseline.json").read_text())
    starts = pd.DataFrame({arm: pd.DataFrame(seeds).mean(axis=1) for arm, seeds in saved.items()})
    starts.rename_axis("robot").to_csv(HERE / "starts.csv", float_format="%.5g")


if __name__ == "__main__":
    main()
