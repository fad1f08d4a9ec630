"""Gather the ablation race's finished runs into the small tables ``read.py`` reads.

    python results/transfer-ablations/collect.py

``--from`` is a race's folder, one branch per task and student, ``<Task>-<student>/``: by default the runs and
starts ``ablation_race.sh`` kept (``kept/race``: each run's evaluations, and its updates in its race folder's
packed table; not its model). Writes ``curves.csv.gz`` (each run's mean deterministic return per robot at each
evaluation), ``training.csv.gz`` (each PPO update's stochastic training return and approximate KL) and
``starts.csv`` (each student's many-draw start per robot: the mean over the evaluation seeds of its folder's
``baseline.json``, told what its runs are told).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from divmorph.pipeline.files import log_file, read_progress

HERE = Path(__file__).resolve().parent
LOGGED = {
    "time/total_timesteps": "timesteps",
    "rollout/ep_rew_mean": "training_return",
    "train/approx_kl": "approx_kl",
}


def updates(run: Path, packed: Path, task: str, student: str, seed: int) -> pd.DataFrame:
    """A run's PPO updates (timesteps, stochastic training return, approximate KL): from its progress logs, or where
    they were left behind, from its race folder's table packed by ``tools/pack_transfer_runs.py``."""
    if (run / "logs").is_dir():
        log = pd.DataFrame(read_progress(run))
        log = log[[c for c in LOGGED if c in log]].rename(columns=LOGGED).dropna(subset=["approx_kl"])
        # a resumed attempt repeats the updates after its checkpoint: the last attempt's count
        return log.drop_duplicates(subset="timesteps", keep="last")
    table = pd.read_csv(packed) if packed.is_file() else pd.DataFrame(columns=["task", "arm", "seed"])
    log = table[(table.task == task) & (table.arm == student) & (table.seed == seed)]
    if log.empty:  # its packing was cut off after its done.json: pack the race folder again
        raise SystemExit(f"{run}: finished, but neither its logs nor {packed} hold its updates")
    return log[list(LOGGED.values())]


def collect(race: Path, out: Path = HERE) -> None:
    """Write the three tables from every finished run and measured start under ``race``."""
    curves, training, starts = [], [], []
    for branch in sorted(p for p in race.iterdir() if p.is_dir()):
        for done in sorted((branch / "transfer").glob("*/*/seed-*/done.json")):
            run = done.parent
            task, student, seed = run.parent.parent.name, run.parent.name, int(run.name.split("-")[1])
            frame = pd.read_csv(log_file(run / "eval.csv")).groupby(["timesteps", "split", "robot"], as_index=False)["return"].mean()
            curves.append(frame.assign(task=task, student=student, seed=seed))
            log = updates(run, race / f"training-{branch.name}.csv.gz", task, student, seed)
            training.append(log.assign(task=task, student=student, seed=seed))
            print(f"{run}: {len(frame)} curve rows, {len(log)} updates")
        baseline = branch / "baseline.json"
        if baseline.is_file():
            task = branch.name.split("-", 1)[0]
            for student, by_seed in json.loads(baseline.read_text()).items():
                frame = pd.DataFrame(by_seed)  # robot x evaluation seed
                starts.append(
                    pd.DataFrame({"task": task, "student": student, "robot": frame.index, "return": frame.mean(axis=1).values, "eval_seeds": frame.shape[1]})
                )
                print(f"{baseline}: {student}'s start, {frame.shape[1]} evaluation seeds")
    if not curves:
        raise SystemExit(f"no finished run under {race}")
    pd.concat(curves).to_csv(out / "curves.csv.gz", index=False, float_format="%.5g")
    pd.concat(training).to_csv(out / "training.csv.gz", index=False, float_format="%.3g")
    if starts:
        pd.concat(starts).to_csv(out / "starts.csv", index=False, float_format="%.5g")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--from", dest="race", type=Path, default=HERE / "kept" / "race", help="a race's folder (default: the kept runs)")
    collect(parser.parse_args().race)


if __name__ == "__main__":
    main()
