"""Which robots a run uses: a profile's splits (train, novel, ood), and the record of them a run
folder keeps (``robot_sets.json``) so a model can be evaluated on the robots it trained on."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from divmorph.pipeline.config import ConfigError, Profile, resolve_path
from unimal_envs.morphology.errors import MorphologyError
from unimal_envs.morphology.loader import is_set_name, morphology_files

from divmorph.pipeline.files import atomic_write_json


def robot_files(robot_set: str, count: int | None, exclude: Sequence[Path] = ()) -> list[Path]:
    """The first ``count`` robots of a set (all when ``None``), leaving out the files in ``exclude``.

    :param robot_set: a set name (shipped ``train``/``novel`` or official ``unimals100-*``, fetched
        once) or a directory (relative paths also from the repository root)
    """
    source: str | Path = robot_set if is_set_name(robot_set) else resolve_path(robot_set)
    excluded = {p.resolve() for p in exclude}
    files = [f for f in morphology_files(source) if f.resolve() not in excluded]
    return files if count is None else files[:count]


#: The robot splits of a run: the robots it trains on, the novel robots of zero-shot evaluation, and
#: an out-of-distribution set reported apart (only when the profile names an ``ood_set``).
SPLITS = ("train", "novel", "ood")


def profile_splits(profile: Profile) -> tuple[str, ...]:
    """The robot splits a profile evaluates on: ``train``, ``novel`` and, with an ``ood_set``, ``ood``."""
    return SPLITS if profile.ood_set is not None else SPLITS[:2]


def profile_robots(profile: Profile, split: str) -> list[Path]:
    """The profile's ``train``, ``novel`` or ``ood`` robots; the other splits never include a training robot.

    :raises ValueError: an unknown split, or ``ood`` in a profile without an ``ood_set``.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown robot split {split!r}; choose from {list(SPLITS)}")
    train = robot_files(profile.train_set, profile.train_robots)
    if split == "train":
        return train
    if split == "ood":
        if profile.ood_set is None:
            raise ValueError(f"profile {profile.name!r} has no out-of-distribution robots (ood_set)")
        return robot_files(profile.ood_set, profile.ood_robots, exclude=train)
    return robot_files(profile.novel_set, profile.novel_robots, exclude=train)


def transfer_eval_robots(profile: Profile, split: str) -> list[Path]:
    """The robots of ``split`` that the transfer runs' evaluation curves roll out: ``transfer.eval_robots``
    of :func:`profile_robots`, spread evenly over its sorted list from the first to the last (every
    robot when it is ``None``).

    Spread, not the first ones: robot files sort by family, and a prefix stands for one family only
    (the first 20 of the official 100 are all ``floor-*`` robots, one family whose returns say little
    of the whole set's).
    """
    robots = profile_robots(profile, split)
    wanted = profile.transfer.eval_robots
    if wanted is None or wanted >= len(robots):
        return robots
    return [robots[i] for i in np.linspace(0, len(robots) - 1, wanted).round().astype(int)]


#: The record of which robots a run trains and evaluates on (at the run folder's root).
ROBOT_SETS = "robot_sets.json"


def trained_robots(folder: str | Path) -> list[Path] | None:
    """The robots a pipeline model was trained on: the ``train`` robots of the run it belongs to,
    read from the nearest ``robot_sets.json`` in ``folder`` or above it (``None`` when there is none,
    e.g. an rl-zoo run). A shipped model then runs on its own robots by default, wherever they live
    on this machine (a set name resolves to this machine's fetched copy).

    :param folder: a model folder (``teachers/FT``, ``student``, ``transfer/<task>/<arm>/seed-0``) or a
        ``model.zip`` inside one.
    :raises ConfigError: the record names robots that its set does not hold here.
    """
    record = _robot_sets_record(folder)
    if record is None:
        return None
    entry = json.loads(record.read_text())["train"]
    available = {f.stem: f for f in robot_files(entry["set"], None)}
    missing = [name for name in entry["robots"] if name not in available]
    if missing:
        raise ConfigError(
            f"{record} names robots of the set {entry['set']!r} that are not there on this machine: "
            f"{missing[:3]}{'...' if len(missing) > 3 else ''}"
        )
    return [available[name] for name in entry["robots"]]


def trained_robot_set(folder: str | Path) -> str | None:
    """The name (or folder) of the robot set a pipeline model was trained on (see :func:`trained_robots`)."""
    record = _robot_sets_record(folder)
    return None if record is None else json.loads(record.read_text())["train"]["set"]


def trained_env_kwargs(folder: str | Path) -> dict[str, Any]:
    """The env arguments the run a pipeline model belongs to made its envs with
    (:func:`profile_env_kwargs` of the profile in the nearest ``run.json`` in ``folder`` or above it;
    empty for an rl-zoo run or a run at the defaults).

    :param folder: a model folder or a ``model.zip`` inside one.
    """
    record = _nearest_record(folder, "run.json")
    if record is None:
        return {}
    configuration = json.loads(record.read_text()).get("configuration", {})
    height = configuration.get("height_reference", "world")
    kwargs: dict[str, Any] = {} if height == "world" else {"height_reference": height}
    if configuration.get("goal_range") is not None:
        kwargs["goal_range"] = float(configuration["goal_range"])
    return kwargs


def trained_instruction(folder: str | Path, task: str | None) -> str | None:
    """The instruction a transfer run's envs gave its model: the one its ``source.json`` records
    (``transfer.task_gates: closest``), else its run's ``transfer.instructions[task]``; ``None``: the
    task's built-in one, and for every folder that is not a transfer run (no ``source.json``).

    :param folder: a model folder or a ``model.zip`` inside one.
    """
    source = _model_folder(folder) / "source.json"
    if not source.is_file():
        return None
    recorded = json.loads(source.read_text()).get("instruction")
    if recorded is not None or task is None:
        return recorded
    record = _nearest_record(folder, "run.json")
    if record is None:
        return None
    configured = json.loads(record.read_text()).get("configuration", {}).get("transfer", {}).get("instructions") or {}
    return configured.get(task)


def _model_folder(folder: str | Path) -> Path:
    """A model folder, given it or a ``model.zip`` inside it (resolved)."""
    folder = Path(folder).resolve()
    return folder.parent if folder.suffix == ".zip" else folder


def _nearest_record(folder: str | Path, name: str) -> Path | None:
    """The nearest file ``name`` (a run's ``run.json``, ``robot_sets.json``) in a model folder or above it."""
    start = _model_folder(folder)
    return next((d / name for d in (start, *start.parents) if (d / name).is_file()), None)


def _robot_sets_record(folder: str | Path) -> Path | None:
    """The nearest ``robot_sets.json`` in ``folder`` (a model folder or a ``model.zip``) or above it."""
    return _nearest_record(folder, ROBOT_SETS)


def robot_set_record(profile: Profile) -> dict[str, Any]:
    """Which robot sets a profile uses, resolved: names, folders, robot counts and, for the official
    sets, the source and checksum manifest they were fetched with (so results name their robots)."""
    record: dict[str, Any] = {}
    for split, name in (("train", profile.train_set), ("novel", profile.novel_set), ("ood", profile.ood_set)):
        if name is None:
            continue
        try:
            files = profile_robots(profile, split)
        except MorphologyError as error:
            if split == "train":
                raise
            # a stage that only trains (a GPU job carrying the training robots) needs no held-out set;
            # the evaluation that does reads it then and fails with the fetch command
            record[split] = {"set": name, "not_on_this_machine": str(error)}
            continue
        folder = files[0].parent.parent if files[0].parent.name == "xml" else files[0].parent
        # Where the set was read on this machine, with the home folder as ~ (no user's paths in results).
        entry: dict[str, Any] = {"set": name, "folder": _portable(folder), "robots": [f.stem for f in files]}
        manifest = folder / "MANIFEST.json"
        if manifest.is_file():
            data = json.loads(manifest.read_text())
            entry["source"] = data.get("source")
            entry["manifest_sha256"] = hashlib.sha256(manifest.read_bytes()).hexdigest()
        record[split] = entry
    return record


def record_robot_sets(profile: Profile, out: Path) -> Path:
    """Write :func:`robot_set_record` to ``out/robot_sets.json`` (atomically) and return its path."""
    path = Path(out) / ROBOT_SETS
    atomic_write_json(path, robot_set_record(profile))
    return path


def _portable(path: Path) -> str:
    """``path`` as another machine can read it: relative to the repository when inside it (the
    shipped sets), else with the user's home folder written as ``~`` (the fetched official sets)."""
    path = path.resolve()
    for base, shown in ((Path(__file__).resolve().parents[2], None), (Path.home(), Path("~"))):
        try:
            relative = path.relative_to(base)
        except ValueError:
            continue
        return str(relative if shown is None else shown / relative)
    return str(path)
