"""The run folder: which stages a run has, where each one's outputs live, and which are done.

Every stage reads and writes a run folder (``runs/<profile>`` or ``--out``) and nothing else; the
stages never import each other, only this module (and the helpers of :mod:`~divmorph.pipeline.files`, :mod:`~divmorph.pipeline.training`
below it). A finished run of any stage holds ``done.json`` (:func:`~divmorph.pipeline.files.is_done`);
``run.json`` at the top records the settings and commands (:mod:`~divmorph.pipeline.provenance`).

==============  ===========================================  ================================================
stage           reads                                        writes
==============  ===========================================  ================================================
teachers        (robots, zoo entries)                        ``teachers/<task>/`` model.zip, vecnormalize.pkl
distill         ``teachers/``                                ``student/``, ``students/<name>/``
hyperdistill    ``teachers/`` (or trains its own)            ``hyperdistill/`` (``teachers/``, ``student/``,
                                                             ``export/``)
grl             (robots, zoo entries)                        ``grl/gen-<g>/agent-<i>/``, ``grl/learngene.json``
transfer        ``teachers/``, ``student/``, ``students/``,  ``transfer/<task>/<arm>/seed-<s>/`` (eval.csv),
                ``grl/learngene.json``                       ``transfer/<task>/metrics.csv``
export          ``student/``, ``students/``, ``transfer/``   ``export/<robot>-<task>/`` (report.json, actors),
                                                             ``export/summary.csv``
evaluate        every model above                            ``evaluate/`` returns.csv, gates.npz
report          every output above                           ``report/``, ``summary.md``
==============  ===========================================  ================================================

A trained model's folder always holds ``model.zip`` and, when it normalises, ``vecnormalize.pkl``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sb3_divmorph.algos.distillation import Teacher
from divmorph.pipeline.config import ConfigError, Profile
from divmorph.pipeline.files import is_done
from divmorph.pipeline.training import stage_model, stage_normalizer
from divmorph.pipeline.students import STUDENTS
from unimal_envs.contract import NOVEL_TASKS, TASK_NAMES, observation_space

#: Each stage's folders in a run.
STAGE_FOLDERS: dict[str, tuple[str, ...]] = {
    "teachers": ("teachers",),
    "distill": ("student", "students"),
    "hyperdistill": ("hyperdistill",),
    "grl": ("grl",),
    "transfer": ("transfer",),
    "export": ("export",),
    "evaluate": ("evaluate",),
}
#: The stages built on each stage's outputs (retrained with it).
DOWNSTREAM: dict[str, tuple[str, ...]] = {
    "teachers": ("distill", "hyperdistill", "grl", "transfer", "export", "evaluate"),
    "distill": ("transfer", "export", "evaluate"),
    "hyperdistill": ("evaluate",),
    "grl": ("transfer", "evaluate"),
    "transfer": ("export", "evaluate"),
    "export": (),
    "evaluate": (),
}


# -- teachers ---------------------------------------------------------------------------------------
#: The job builder of one teacher (:class:`~divmorph.pipeline.grid.Job`), for the stages that need
#: teachers trained (HyperDistill's) or rebuilt untrained (evaluate): a name, so that no stage imports another.
TEACHER_RUN = "divmorph.pipeline.teachers:teacher_run"


def teacher_folder(out: Path, task: str, root: str = "teachers") -> Path:
    """``teachers/<task>/`` (``root``: another policy's teachers, e.g. ``hyperdistill/teachers``)."""
    return Path(out) / root / task


def load_teachers(profile: Profile, out: Path, root: str = "teachers") -> dict[int, Teacher]:
    """``{task index: Teacher}`` for every teacher of the profile (in ``root``); a missing one is an error."""
    teachers = {}
    for task in profile.teachers.tasks:
        folder = teacher_folder(out, task, root)
        if not is_done(folder):
            raise FileNotFoundError(f"teacher for {task} not found in {folder} (no done.json); run `divmorph teachers --out {out}` first")
        teachers[TASK_NAMES.index(task)] = Teacher.load(
            stage_model(folder), stage_normalizer(folder), name=task, observation_space=observation_space()
        )
    return teachers


# -- students ---------------------------------------------------------------------------------------
def student_folder(out: Path, name: str = "divmorph") -> Path:
    """``student/`` for the DivMorph student, ``students/<name>/`` for the others."""
    if name not in STUDENTS:
        raise ConfigError(f"unknown student {name!r}; students: {list(STUDENTS)}")
    return Path(out) / "student" if name == "divmorph" else Path(out) / "students" / name


# -- GRL ----------------------------------------------------------------------------------------------
def grl_folder(out: Path) -> Path:
    return Path(out) / "grl"


def agent_folder(out: Path, generation: int, index: int) -> Path:
    return grl_folder(out) / f"gen-{generation}" / f"agent-{index}"


def learngene_file(out: Path) -> Path:
    return grl_folder(out) / "learngene.json"


def read_learngene(out: Path) -> dict[str, Any]:
    """The evolved learngene: ``{"units", "agent", "generation", "task", "fitness", "folder"}``."""
    path = learngene_file(out)
    if not path.is_file():
        raise FileNotFoundError(f"no evolved GRL learngene in {path}; run `divmorph grl --out {out}` first")
    return json.loads(path.read_text())


# -- evaluation ---------------------------------------------------------------------------------------
def evaluation_label(folder: Path) -> tuple[Path, str, int | None] | None:
    """``(run folder, model label, transfer seed)`` under which the evaluation stage records the
    model of a stage ``folder`` (``teachers/FT`` -> ``teacher``, ``student`` -> ``student``,
    ``students/<name>`` -> ``student-<name>``, ``hyperdistill/student`` -> ``hyperdistill``,
    ``transfer/<task>/<arm>/seed-<s>`` -> ``transfer-<arm>``); ``None`` for a folder of no run."""
    folder = Path(folder).resolve()
    parts = folder.parts
    for depth in range(1, 5):
        run, tail = Path(*parts[:-depth]), parts[-depth:]
        if not (run / "run.json").is_file():
            continue
        if tail[0] == "teachers" and len(tail) == 2:
            return run, "teacher", None
        if tail == ("student",):
            return run, "student", None
        if tail[0] == "students" and len(tail) == 2:
            return run, f"student-{tail[1]}", None
        if tail == ("hyperdistill", "student"):
            return run, "hyperdistill", None
        if tail[0] == "transfer" and len(tail) in (3, 4):
            seed = int(tail[3].removeprefix("seed-")) if len(tail) == 4 else 0
            return run, f"transfer-{tail[2]}", seed
    return None


# -- transfer -----------------------------------------------------------------------------------------
def transfer_folder(out: Path, task: str, arm: str, seed: int = 0) -> Path:
    """``transfer/<task>/<arm>/seed-<seed>/``; a run held in the arm's folder itself (no ``seed-<n>/``)
    is seed 0, so such a run folder resumes rather than starting again."""
    base = Path(out) / "transfer" / task / arm
    if seed == 0 and ((base / "done.json").is_file() or (base / "checkpoints").is_dir()):
        return base
    return base / f"seed-{seed}"


def transfer_tasks(profile: Profile, out: Path) -> list[str]:
    """The profile's transfer tasks, then any other novel task the run folder holds transfer runs of
    (``divmorph transfer --task PointNav`` outside the profile is evaluated and reported too)."""
    found = sorted(p.name for p in (Path(out) / "transfer").glob("*") if p.is_dir() and p.name in NOVEL_TASKS)
    return list(dict.fromkeys([*profile.transfer.tasks, *found]))


def transfer_seeds(profile: Profile, out: Path, task: str, arm: str) -> list[int]:
    """The profile's seeds, then any other seed the run folder holds a run of for ``task`` and ``arm``."""
    found = sorted(
        int(p.name.split("-", 1)[1]) for p in (Path(out) / "transfer" / task / arm).glob("seed-*") if p.name.split("-", 1)[1].isdigit()
    )
    return list(dict.fromkeys([*profile.transfer.seeds, *found]))


# -- export -------------------------------------------------------------------------------------------
def export_reports(out: Path) -> list[Path]:
    """Every ``report.json`` of the run's exports (all students)."""
    folder = Path(out) / "export"
    return sorted([*folder.glob("*/report.json"), *folder.glob("*/*/report.json")])
