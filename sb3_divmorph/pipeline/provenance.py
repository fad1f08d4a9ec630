"""What produced a run folder: ``run.json`` (resolved profile, robots, versions, commit, device used).

Every ``divmorph`` stage command writes the record on its first use of a run folder and checks it
on every later one: a run is continued only with the configuration it was started with. A profile
that differs (another profile, another seed, other robots, another budget...) stops the command
with the differing keys listed, before anything is trained, skipped or reported, so a summary can
never describe settings its models were not trained with. ``--force`` accepts the new settings
(the stages already finished are kept; delete a stage's folder to retrain it).
"""

from __future__ import annotations

import dataclasses
import json
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from sb3_divmorph.pipeline.config import ConfigError, Profile
from sb3_divmorph.pipeline.runs import atomic_write_json, resolve_device, robot_set_record

RECORD = "run.json"
#: packages whose versions a result depends on
PACKAGES = ("divmorph", "torch", "stable-baselines3", "gymnasium", "mujoco", "numpy")


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        return subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=True).stdout.strip()
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


def _differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new))
        return [d for k in keys for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix.rstrip('.')}: {old!r} -> {new!r}"]


def check_and_record(out: Path, profile: Profile, command: str, force: bool = False) -> dict[str, Any]:
    """Compare ``profile`` with the configuration recorded in ``out/run.json`` and (re)write the record.

    :param out: the run folder (it may not exist yet).
    :param command: the command line, appended to the record's history.
    :param force: accept a configuration that differs from the recorded one.
    :raises ConfigError: the configuration differs and ``force`` is off; the message lists the keys.
    """
    path = Path(out) / RECORD
    config = configuration(profile)
    device = resolve_device(profile.device)
    previous = json.loads(path.read_text()) if path.is_file() else None
    if previous is not None and previous["configuration"] != config and not force:
        changed = _differences(previous["configuration"], config)
        raise ConfigError(
            f"{out} was run with other settings ({path}); differing keys:\n  " + "\n  ".join(changed)
            + "\nUse another --out for the new settings, or --force to continue this run with them "
            "(finished stages are kept; delete a stage's folder to retrain it)."
        )
    record = {
        "configuration": config,
        "device_used": device,
        "robots": robot_set_record(profile),
        "versions": _versions(),
        "git_commit": _git_commit(),
        "machine": f"{platform.node()} ({platform.machine()}, {platform.system()})",
        "history": [*(previous or {}).get("history", []), {"command": command, "time": time.strftime("%Y-%m-%d %H:%M:%S"), "forced": bool(force and previous is not None and previous["configuration"] != config)}],
    }
    atomic_write_json(path, record)
    return record
