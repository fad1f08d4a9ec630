"""Give a race's runs folder on a new machine what its unstarted jobs read from the finished ones.

    PYTHONPATH=WORKTREE python results/transfer-race/restore_runs.py RUNS KEEP

A many-draw start (``race.py``'s ``<task>-<arm>-start``) evaluates the model its arm's seed-0 run began from, named
in that run's ``source.json``, inside the task's branched run folder. On the machine that ran seed 0 both are in
RUNS; on a new one only the packed run in KEEP is, and the start would wait for ever. For every packed seed-0 run
whose folder RUNS lacks, this branches the task's folder from ``RUNS/source`` as the run's first command did and
puts the packed ``source.json`` back. It writes nothing a run reads as progress (no checkpoint, no ``done.json``),
so no finished run restarts and no unfinished one resumes from it; it is a no-op where RUNS already has the folder.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from divmorph.pipeline.branch import branch

#: The command ``finetune_known_task.py`` records when it branches a task's folder.
BRANCH_COMMAND = "python results/finetune-known-task/finetune_known_task.py"


def restore(runs: Path, keep: Path) -> list[Path]:
    """Restore each packed seed-0 run's ``source.json`` (and its task folder) into ``runs``; returns those written."""
    if not (runs / "source" / "run.json").is_file():
        raise SystemExit(f"no race source in {runs}: run python results/transfer-race/make_source.py {runs / 'source'} first")
    written = []
    for packed in sorted(keep.glob("*/transfer/*/*/seed-0/source.json")):
        seed_folder = packed.parent
        folder = runs / seed_folder.relative_to(keep)
        if folder.exists():
            continue
        task_folder = runs / seed_folder.relative_to(keep).parts[0]
        if not (task_folder / "run.json").is_file():
            branch(runs / "source", task_folder, ("teachers", "distill"), command=BRANCH_COMMAND)
        folder.mkdir(parents=True)
        shutil.copyfile(packed, folder / "source.json")
        written.append(folder / "source.json")
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, help="the race's runs folder (RUNS/source made first)")
    parser.add_argument("keep", type=Path, help="the tracked folder of the finished runs, packed")
    args = parser.parse_args(argv)
    for path in restore(args.runs, args.keep):
        print(f"restored {path}")


if __name__ == "__main__":
    main()
