"""A run folder that reuses another run's finished stages (``divmorph branch``).

An experiment downstream of a finished run (a longer transfer budget, other transfer tasks or
seeds) needs that run's teachers and students: retraining them would cost hours and give other
models. ``branch`` creates a new run folder in which each *finished* run of the reused stages
(a teacher, a student, GRL's evolution, the HyperDistill student) is a relative symbolic link into
the source run, and whose ``run.json`` starts as the source's record (configuration and command
history, with the branch appended). Provenance then treats the linked stages as begun in the
branch: a command that changes their settings there is refused, while the stages downstream of
them run in the branch under new settings, e.g.::

    divmorph branch --from runs/demo --out runs/demo-transfer-300k
    divmorph transfer --run runs/demo-transfer-300k --set transfer.n_timesteps=300000

Nothing is written into the source: unfinished runs are not linked (a student still distilling
in the source is trained afresh in the branch if the branch needs it), and ``--redo`` in the
branch moves its links, not the folders they point to.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path

from divmorph.pipeline.config import ConfigError
from divmorph.pipeline.files import DONE, atomic_write_json
from divmorph.pipeline.provenance import RECORD, STAGE_FOLDERS
from divmorph.pipeline.retired import format_problem

#: The stages a branch can reuse: those trained before transfer, which every later stage reads.
REUSABLE_STAGES = ("teachers", "distill", "hyperdistill", "grl")


def finished_runs(folder: Path) -> list[Path]:
    """``folder`` itself when it is a finished run, else its finished sub-runs (``teachers/FT``...)."""
    if (folder / DONE).is_file():
        return [folder]
    if not folder.is_dir():
        return []
    return [child for child in sorted(folder.iterdir()) if child.is_dir() and (child / DONE).is_file()]


def branch(source: Path, out: Path, stages: Sequence[str] = REUSABLE_STAGES, command: str = "divmorph branch") -> list[Path]:
    """Create run folder ``out`` reusing the finished runs of ``stages`` in run folder ``source``.

    :param source: a run folder (with ``run.json``).
    :param out: the new run folder; it must not exist or be empty.
    :param stages: stages whose finished runs are linked (of :data:`REUSABLE_STAGES`).
    :param command: the command line, appended to the record's history.
    :return: the links created, in ``out``.
    :raises FileNotFoundError: ``source`` is not a run folder.
    :raises ConfigError: ``out`` holds files, is ``source``, or a stage is not reusable.
    """
    source, out = Path(source), Path(out)
    if not (source / RECORD).is_file():
        raise FileNotFoundError(f"{source} is not a run folder: it has no {RECORD}")
    unknown = [stage for stage in stages if stage not in REUSABLE_STAGES]
    if unknown:
        raise ConfigError(f"stage(s) {unknown} cannot be reused; reusable stages: {list(REUSABLE_STAGES)}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{out} already exists and is not an empty folder: branch into a new one")
    if out.resolve() == source.resolve():
        raise ConfigError("a run cannot branch into itself")
    record = json.loads((source / RECORD).read_text())
    problem = format_problem(record, source / RECORD)
    if problem is not None:
        raise ConfigError(problem)
    runs = [run for stage in stages for folder in STAGE_FOLDERS[stage] for run in finished_runs(source / folder)]
    if not runs:
        raise ConfigError(f"{source} has no finished run of the stages {list(stages)} to reuse")

    out.mkdir(parents=True, exist_ok=True)
    links = []
    for run in runs:
        link = out / run.relative_to(source)
        link.parent.mkdir(parents=True, exist_ok=True)
        # relative, so that the pair of folders can move (or be cloned) together
        link.symlink_to(os.path.relpath(run.absolute(), link.parent.absolute()), target_is_directory=True)
        links.append(link)
    if (source / "robot_sets.json").is_file():
        shutil.copyfile(source / "robot_sets.json", out / "robot_sets.json")
    # the rules the linked stages ran under stay on record; the branch's own stages run under today's
    record["retired"] = {key: value for key, value in record.get("retired", {}).items() if key.split(".")[0] in stages}
    record["history"] = [
        *record.get("history", []),
        {
            "command": command,
            "time": time.strftime("%Y-%m-%d %H:%M:%S"),
            "changed": [],
            "forced": False,
            "retrained": [],
            "superseded": None,
            "branched_from": str(source),
            "linked": [str(link.relative_to(out)) for link in links],
        },
    ]
    atomic_write_json(out / RECORD, record)
    return links
