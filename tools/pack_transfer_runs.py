"""Pack the finished transfer runs of a run folder into a recorded-results folder, without their models.

    python tools/pack_transfer_runs.py results/transfer-pointnav/runs-600k /work/race600/scratch=scratch

A race at the 600k budget is dozens of runs, each a 1 MB model and a few MB of logs: more than the
repository's tracked-size limit (``tests/test_tree_size.py``) holds. What a reading of the race needs is
smaller. For each finished run (``transfer/<task>/<arm>/seed-<n>/done.json``) of the run folder this keeps,
under ``<results>/<variant>/transfer/<task>/<arm>/seed-<n>/``:

- ``eval.csv.gz``: every evaluation's episodes (returns rounded to 0.01, what every reading prints);
- ``done.json`` and ``source.json`` as written;

and per variant ``<results>/training-<variant>.csv.gz``: each PPO update's stochastic training return,
critic explained variance, KL and clip fraction (rounded to 5 digits), one row per update, merged with the
rows already there (a run packed again replaces its rows). The gzip is deterministic (no name, no
timestamp), so packing the same runs twice writes the same bytes. Runs without ``done.json`` are skipped
(they are still running, or were cut off: a transfer resumes from its checkpoints).
"""

from __future__ import annotations

import argparse
import gzip
import io
import shutil
from pathlib import Path

import pandas as pd

from divmorph.pipeline.files import log_file, read_progress

# The progress.csv columns kept, and their names in the training table.
TRAINING_COLUMNS = {
    "time/total_timesteps": "timesteps",
    "rollout/ep_rew_mean": "training_return",
    "train/explained_variance": "explained_variance",
    "train/approx_kl": "approx_kl",
    "train/clip_fraction": "clip_fraction",
}
KEY = ["variant", "task", "arm", "seed", "timesteps"]


def write_gzip_csv(frame: pd.DataFrame, path: Path) -> None:
    """Write ``frame`` as a gzip CSV whose bytes depend only on its content."""
    buffer = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buffer, compresslevel=9, mtime=0) as f:
        f.write(frame.to_csv(index=False).encode())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buffer.getvalue())


def pack_run(run: Path, target: Path) -> pd.DataFrame:
    """Copy one finished run's evaluations and records into ``target``; return its training rows."""
    found = log_file(run / "eval.csv")
    if found is None:
        raise FileNotFoundError(f"{run}: finished but no eval.csv (nor eval.csv.gz) -- is this a transfer run folder?")
    evaluations = pd.read_csv(found)
    evaluations["return"] = evaluations["return"].round(2)
    write_gzip_csv(evaluations, target / "eval.csv.gz")
    for name in ("done.json", "source.json"):
        if (run / name).is_file():
            shutil.copyfile(run / name, target / name)
    progress = pd.DataFrame(read_progress(run))  # every logs/run-* attempt of a resumed run, in order
    missing = sorted(set(TRAINING_COLUMNS) - set(progress.columns))
    if missing:
        raise ValueError(f"{run}: its progress.csv lacks {missing} -- not a PPO transfer run?")
    rows = progress[list(TRAINING_COLUMNS)].rename(columns=TRAINING_COLUMNS).dropna(subset=["clip_fraction"])
    rows = rows.drop_duplicates("timesteps", keep="last").round(5)
    rows["timesteps"] = rows["timesteps"].astype(int)
    return rows


def pack(results: Path, source: Path, variant: str) -> list[str]:
    """Pack every finished run of ``source`` as ``variant`` under ``results``; return the runs packed."""
    packed, training = [], []
    for done in sorted(source.glob("transfer/*/*/seed-*/done.json")):
        run = done.parent
        task, arm, seed = run.parent.parent.name, run.parent.name, int(run.name.removeprefix("seed-"))
        rows = pack_run(run, results / variant / "transfer" / task / arm / run.name)
        rows.insert(0, "seed", seed)
        rows.insert(0, "arm", arm)
        rows.insert(0, "task", task)
        rows.insert(0, "variant", variant)
        training.append(rows)
        packed.append(f"{task}/{arm}/seed-{seed}")
    if training:
        table_path = results / f"training-{variant}.csv.gz"
        new = pd.concat(training, ignore_index=True)
        if table_path.is_file():
            old = pd.read_csv(table_path)
            runs = set(new[["task", "arm", "seed"]].itertuples(index=False, name=None))
            keep = [tuple(r) not in runs for r in old[["task", "arm", "seed"]].itertuples(index=False, name=None)]
            new = pd.concat([old[keep], new], ignore_index=True)
        write_gzip_csv(new.sort_values(KEY).reset_index(drop=True), table_path)
    return packed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="the recorded-results folder, e.g. results/transfer-pointnav/runs-600k")
    parser.add_argument("sources", nargs="+", help="RUN_FOLDER=VARIANT: a run folder and the variant name its runs are kept under")
    args = parser.parse_args(argv)
    for spec in args.sources:
        folder, _, variant = spec.rpartition("=")
        if not folder or not variant:
            parser.error(f"{spec!r}: expected RUN_FOLDER=VARIANT")
        packed = pack(args.results, Path(folder), variant)
        print(f"{variant}: {len(packed)} finished runs packed from {folder}" + (f" ({', '.join(packed)})" if packed else ""))


if __name__ == "__main__":
    main()
