"""What produced a run folder: ``run.json`` (resolved profile, robots, versions, commit, device used).

Every ``divmorph`` stage command writes the record on its first use of a run folder and checks it
on every later one: a stage already begun is reused (skipped when finished, resumed otherwise) only
under the settings it was begun with. A profile that changes keys a begun stage depends on
(:data:`STAGE_KEYS`: another seed, other robots, another budget...) stops the command with the
stages and differing keys listed, before anything is trained, skipped or reported, so a summary can
never describe settings its models were not trained with. ``--redo STAGE`` retrains a stage (and
the begun stages built on it) under the new settings, ``--force`` does so for every stage the
change touches; the old folders are moved to ``superseded/<time>/``, never deleted. A change that
touches no begun stage (say, the transfer budget before any transfer ran) is simply recorded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import platform
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

from divmorph.pipeline.config import ConfigError, Profile, apply_overrides, profile_from_dict
from divmorph.pipeline.folders import DOWNSTREAM, STAGE_FOLDERS  # noqa: F401 -- re-exported
from divmorph.pipeline.envs import resolve_device
from divmorph.pipeline.files import DONE, atomic_write_json, read_done
from divmorph.pipeline.retired import RECORD_FORMAT, format_problem, retired_changes
from divmorph.pipeline.robots import robot_set_record
from divmorph.pipeline.training import reopen

RECORD = "run.json"
#: where ``--redo`` / ``--force`` move the folders of the stages they retrain
SUPERSEDED = "superseded"

_BASE = ("seed", "train_set", "train_robots", "max_episode_steps", "height_reference")
_NOVEL = ("novel_set", "novel_robots")
#: The profile keys each stage's outputs depend on: its own section and those of what it is built on.
STAGE_KEYS: dict[str, tuple[str, ...]] = {
    "teachers": (*_BASE, "teachers"),
    "distill": (*_BASE, "teachers", "student", "distill"),
    "hyperdistill": (*_BASE, "teachers", "hyperdistill"),
    "grl": (*_BASE, "teachers", "grl"),
    "transfer": (*_BASE, *_NOVEL, "teachers", "student", "distill", "grl", "transfer"),
    "export": (*_BASE, *_NOVEL, "teachers", "student", "distill", "transfer", "export"),
    "evaluate": (*_BASE, *_NOVEL, "ood_set", "ood_robots", "teachers", "student", "distill", "hyperdistill", "grl", "transfer", "evaluate"),
}
#: The stages a larger budget can continue (``--continue STAGE``): PPO runs, whose final model holds
#: all the run's state (DAgger's dataset and GRL's population are not kept once a stage finishes).
EXTENDABLE: dict[str, str] = {"teachers": "teachers.n_timesteps", "transfer": "transfer.n_timesteps"}
#: packages whose versions a result depends on
PACKAGES = ("divmorph", "torch", "stable-baselines3", "gymnasium", "mujoco", "numpy")


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        return subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def _versions() -> dict[str, str | None]:
    versions: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def configuration(profile: Profile) -> dict[str, Any]:
    """The profile as plain values (what a run's models depend on)."""
    return json.loads(json.dumps(dataclasses.asdict(profile), default=str))


def recorded_profile(path: Path, overrides: dict[str, Any] | None = None) -> Profile:
    """The profile a run was run with, from its ``run.json`` (``overrides`` applied, validated like the YAML).

    :raises ConfigError: the record is of an older format (the message names ``divmorph migrate``),
        or its configuration does not parse.
    """
    record = json.loads(Path(path).read_text())
    problem = format_problem(record, path)
    if problem is not None:
        raise ConfigError(problem)
    values = dict(record["configuration"])
    name = values.pop("name")
    try:
        return profile_from_dict(name, apply_overrides(values, overrides or {}))
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def _with_defaults(recorded: dict[str, Any]) -> dict[str, Any]:
    """A recorded configuration with the defaults of keys added to the profile since it was
    recorded (a new key at its default changes nothing a run did); as recorded if it no longer parses."""
    values = dict(recorded)
    try:
        return configuration(profile_from_dict(values.pop("name", "recorded"), values))
    except ConfigError:
        return recorded


def _differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new))
        return [d for k in keys for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix.rstrip('.')}: {old!r} -> {new!r}"]


def begun_stages(out: Path) -> list[str]:
    """The stages that have begun in run folder ``out`` (a folder of theirs holds anything)."""
    out = Path(out)
    return [stage for stage, folders in STAGE_FOLDERS.items() if any((out / f).is_dir() and any((out / f).iterdir()) for f in folders)]


def stage_changes(old: dict[str, Any], new: dict[str, Any], stage: str) -> list[str]:
    """The differing keys between two configurations that ``stage``'s outputs depend on."""
    return [d for key in STAGE_KEYS[stage] for d in _differences({key: old.get(key)}, {key: new.get(key)})]


def supersede(out: Path, stages: list[str]) -> Path | None:
    """Move the folders of ``stages`` to ``out/superseded/<time>/`` (kept, never deleted); returns it."""
    out = Path(out)
    moved = [out / f for stage in stages for f in STAGE_FOLDERS[stage] if (out / f).exists()]
    if not moved:
        return None
    target = out / SUPERSEDED / time.strftime("%Y%m%d-%H%M%S")
    target.mkdir(parents=True, exist_ok=True)
    for folder in moved:
        shutil.move(str(folder), str(target / folder.name))
    return target


def restore_superseded(out: Path, record: dict[str, Any], previous_record: str | None) -> Path | None:
    """Undo :func:`check_and_record`'s retraining after the command failed: move the stage folders it
    superseded back into ``out`` (what the failed attempt wrote goes to ``superseded/<time>-failed/``)
    and put the previous ``run.json`` back, so a failure never leaves a run without its good results.

    :param record: what :func:`check_and_record` returned.
    :param previous_record: the text of ``run.json`` before it (``None``: there was none).
    :returns: the folder the failed attempt's outputs went to, or ``None`` when nothing was superseded.
    """
    out = Path(out)
    moved = record["history"][-1].get("superseded")
    if not moved or not Path(moved).is_dir():
        return None
    failed = out / SUPERSEDED / (time.strftime("%Y%m%d-%H%M%S") + "-failed")
    for folder in sorted(Path(moved).iterdir()):
        if (out / folder.name).exists():
            failed.mkdir(parents=True, exist_ok=True)
            shutil.move(str(out / folder.name), str(failed / folder.name))
        shutil.move(str(folder), str(out / folder.name))
    Path(moved).rmdir()
    if previous_record is not None:
        (out / RECORD).write_text(previous_record)
    return failed if failed.exists() else None


def check_and_record(
    out: Path,
    profile: Profile,
    command: str,
    force: bool = False,
    redo: tuple[str, ...] | list[str] = (),
    extend: tuple[str, ...] | list[str] = (),
    trains: bool = True,
) -> dict[str, Any]:
    """Compare ``profile`` with the configuration recorded in ``out/run.json``, retrain what must be
    retrained, and (re)write the record.

    :param out: the run folder (it may not exist yet).
    :param command: the command line, appended to the record's history.
    :param force: retrain every begun stage whose settings changed (and the stages built on it).
    :param redo: retrain these stages (and the begun stages built on them), changed or not.
    :param extend: continue these stages' finished runs to a larger budget (:data:`EXTENDABLE`):
        the budget may grow and nothing else of theirs change; the stages built on them still see
        the change (retrain them with ``redo``, or use another run folder).
    :param trains: the command may train a begun stage (``False``: it reads, exports or evaluates the
        finished ones): a begun stage that ran under a retired rule (the record's ``retired``) is then
        a change, since today's code would go on under another rule.
    :raises ConfigError: a begun stage's settings changed and neither ``force`` nor ``redo`` covers
        it (the message lists the stages and keys); an unknown stage in ``redo``.
    """
    unknown = [stage for stage in redo if stage not in STAGE_KEYS]
    if unknown:
        raise ConfigError(f"unknown stage(s) {unknown} for --redo; stages: {list(STAGE_KEYS)}")
    not_extendable = [stage for stage in extend if stage not in EXTENDABLE]
    if not_extendable:
        raise ConfigError(
            f"--continue takes {list(EXTENDABLE)}, not {not_extendable}: a finished distillation or GRL evolution keeps "
            "no dataset or population to continue from (--redo it with the larger budget)"
        )
    # commands started side by side on one run (a worker per core) each append to its history
    with _locked(Path(out)):
        return _check_and_record(out, profile, command, force, redo, extend, trains)


def _extended_stages(
    out: Path, recorded: dict[str, Any] | None, config: dict[str, Any], changed: dict[str, list[str]], extend
) -> list[str]:
    """Check that each stage of ``extend`` only grows its budget; drop it from ``changed``."""
    done = []
    for stage in extend:
        key = EXTENDABLE[stage]
        section, name = key.split(".")
        old = (recorded or {}).get(section, {}).get(name)
        new = config[section][name]
        others = [k for k in changed.get(stage, []) if not k.startswith(f"{key}:")]
        if others:
            raise ConfigError(f"--continue {stage} continues a larger budget only; other settings of it changed: {'; '.join(others)}")
        if old is None or new < old:
            raise ConfigError(
                f"--continue {stage} needs a larger {key} than the run's {old}, got {new} (e.g. --set {key}={2 * (old or 1)})"
            )
        linked = [f for f in STAGE_FOLDERS[stage] if any(p.is_symlink() for p in (Path(out) / f).rglob("*"))]
        if linked:
            raise ConfigError(
                f"--continue {stage}: {out} is a branch whose {stage} are links into their source; continue them in the source run"
            )
        changed.pop(stage, None)
        done.append(stage)
    return done


def _check_and_record(
    out: Path,
    profile: Profile,
    command: str,
    force: bool,
    redo: tuple[str, ...] | list[str],
    extend: tuple[str, ...] | list[str] = (),
    trains: bool = True,
) -> dict[str, Any]:
    path = Path(out) / RECORD
    config = configuration(profile)
    device = resolve_device(profile.device)
    if profile.device == "auto":
        print(f"[provenance] device auto -> {device} (recorded in {path.name} as device_used)")
    previous = json.loads(path.read_text()) if path.is_file() else None
    if previous is not None and (problem := format_problem(previous, path)) is not None:
        raise ConfigError(problem)
    begun = begun_stages(out)
    recorded = _with_defaults(previous["configuration"]) if previous else None
    # a stage trained under a retired rule is a change to a command that trains: today's code would go on under another rule
    changed = (
        {stage: (retired_changes(previous, stage) if trains else []) + stage_changes(recorded, config, stage) for stage in begun}
        if previous is not None and recorded is not None
        else {}
    )
    changed = {stage: keys for stage, keys in changed.items() if keys}
    extended = _extended_stages(out, recorded, config, changed, [stage for stage in extend if stage in begun])
    blocked = {stage: keys for stage, keys in changed.items() if stage not in redo and not force}
    if blocked:
        raise ConfigError(
            f"{out} holds stages begun with other settings ({path}):\n  "
            + "\n  ".join(f"{stage}: " + "; ".join(keys) for stage, keys in blocked.items())
            + f"\nUse another --out for the new settings, or retrain: --redo {' --redo '.join(blocked)} (or --force for all of "
            f"them); the old folders are kept in {Path(out) / SUPERSEDED}/."
        )
    retrain = [stage for stage in begun if stage in redo or stage in changed or any(stage in DOWNSTREAM[s] for s in (*redo, *changed))]
    moved = supersede(out, retrain)
    if moved is not None:
        print(f"[provenance] retraining {', '.join(retrain)}: their previous folders moved to {moved}")
    for stage in extended:
        budget = config[EXTENDABLE[stage].split(".")[0]]["n_timesteps"]
        for marker in sorted(p for f in STAGE_FOLDERS[stage] for p in (Path(out) / f).rglob(DONE)):
            if read_done(marker.parent).get("num_timesteps", budget) < budget and (step := reopen(marker.parent)) is not None:
                print(f"[provenance] {marker.parent}: finished at step {step:,}, continues to {budget:,}")
    retired = {key: value for key, value in (previous or {}).get("retired", {}).items() if key.split(".")[0] not in retrain}
    record = {
        "format": RECORD_FORMAT,
        "configuration": config,
        "device_used": device,
        "robots": robot_set_record(profile),
        "versions": _versions(),
        "git_commit": _git_commit(),
        "machine": f"{platform.node()} ({platform.machine()}, {platform.system()})",
        **({"retired": retired} if retired else {}),
        "history": [
            *(previous or {}).get("history", []),
            {
                "command": command,
                "time": time.strftime("%Y-%m-%d %H:%M:%S"),
                "changed": _differences(recorded, config) if previous else [],
                "forced": bool(force and changed),
                "retrained": retrain,
                "continued": extended,
                "superseded": str(moved) if moved else None,
            },
        ],
    }
    atomic_write_json(path, record)
    return record


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    """An exclusive lock on the run ``out``'s record for the block (a lock file in the temporary folder,
    so that the run folder gets nothing new); none where ``fcntl`` is missing (Windows)."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    name = hashlib.sha1(str(Path(out).resolve()).encode()).hexdigest()[:16]
    with open(Path(tempfile.gettempdir()) / f"divmorph-run-{name}.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
