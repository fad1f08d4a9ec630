"""Gather the finished runs of the recipes' run folders (not tracked) into the small tables ``read.py``
reads: ``curves.csv.gz`` (each run's mean deterministic return per robot at each evaluation) and
``training.csv.gz`` (each PPO update's stochastic training return and approximate KL).

    python results/transfer-recipes/collect.py --from runs/recipes-free runs/recipes-kl runs/recipes-sv

A run is named by its arm and the one setting its folder varies (``rule.md``): ``F`` (recipes-free:
divmorph-finetuned, rotations frozen), ``K`` / ``Km`` (recipes-kl: the fixed-gate arm / MetaMorph⚗ at a
KL of 0.01 per update), ``S`` (recipes-sv: FINE's singular values), ``KIND`` (recipes-kind: the task tailors
restarted), ``A`` (recipes-adapter), ``<F|G|L|GL>-Escape`` (the controls on Escape; L, GL: Incline's gates).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
LOGGED = {
    "time/total_timesteps": "timesteps",
    "rollout/ep_rew_mean": "training_return",
    "train/approx_kl": "approx_kl",
}
VARIANTS = {
    ("recipes-free", "divmorph-finetuned"): "F",
    ("recipes-kl", "divmorph"): "K",
    ("recipes-kl", "distilled"): "Km",
    ("recipes-sv", "divmorph"): "S",
    ("recipes-kind", "divmorph"): "KIND",
    ("recipes-adapter", "divmorph"): "A",
    ("recipes-kl-escape", "divmorph"): "K-Escape",
    ("recipes-kl-exploration", "divmorph"): "K-Exploration",
    ("recipes-free-escape", "divmorph-finetuned"): "F-Escape",
    ("recipes-g-escape", "divmorph"): "G-Escape",
    ("recipes-low-escape", "divmorph"): "L-Escape",
    ("recipes-g-low-escape", "divmorph"): "GL-Escape",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--from", dest="sources", type=Path, nargs="+", required=True)
    args = parser.parse_args()
    curves, training = [], []
    for source in args.sources:
        for done in sorted((source / "transfer").glob("*/*/seed-*/done.json")):
            run = done.parent
            arm, seed = run.parent.name, int(run.name.split("-")[1])
            variant = VARIANTS[(source.name, arm)]
            frame = pd.read_csv(run / "eval.csv").groupby(["timesteps", "split", "robot"], as_index=False)["return"].mean()
            curves.append(frame.assign(variant=variant, seed=seed))
            log = pd.concat(pd.read_csv(p) for p in sorted((run / "logs").glob("run-*/progress.csv")))
            log = log[[c for c in LOGGED if c in log]].rename(columns=LOGGED).dropna(subset=["approx_kl"])
            training.append(log.assign(variant=variant, seed=seed))
            print(f"{run}: {variant}, {len(frame)} curve rows, {len(log)} updates")
    pd.concat(curves).to_csv(HERE / "curves.csv.gz", index=False, float_format="%.5g")
    pd.concat(training).to_csv(HERE / "training.csv.gz", index=False, float_format="%.3g")


if __name__ == "__main__":
    main()
