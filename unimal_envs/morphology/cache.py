"""Where the official robot sets live on this machine, and whether they are there.

The names, the cache folder and the lookup of a fetched set; :mod:`unimal_envs.morphology.official`
fetches and verifies the sets, :mod:`unimal_envs.morphology.loader` resolves set names through
:func:`official_set_dir`. Nothing here reads a robot, so both can stand on it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from unimal_envs.morphology.errors import MorphologyError

#: Written last into a fetched set's folder: its presence means the set is complete.
MANIFEST = "MANIFEST.json"


@dataclass(frozen=True)
class OfficialSet:
    """One official set.

    :param name: the set name used everywhere a set name is accepted.
    :param short: its name on the ``fetch --sets`` command line.
    :param folder: its folder under ``data/`` in the authors' repository.
    :param count: the number of robots it must hold.
    """

    name: str
    short: str
    folder: str
    count: int


OFFICIAL_SETS = {
    s.name: s
    for s in (
        OfficialSet("unimals100-train", "train", "train", 100),
        OfficialSet("unimals100-test", "test", "test", 102),
        OfficialSet("unimals100-mutants", "mutants", "train_mutate_1000", 1000),
    )
}
SHORT_NAMES = {s.short: s for s in OFFICIAL_SETS.values()}


def cache_root(cache: str | Path | None = None) -> Path:
    """Where the official sets are cached: ``cache``, else ``$UNIMAL_DATA``, else the user cache folder.

    :param cache: an explicit folder (overrides the environment).
    """
    if cache is not None:
        return Path(cache).expanduser()
    if os.environ.get("UNIMAL_DATA"):
        return Path(os.environ["UNIMAL_DATA"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "unimal_envs"


def fetch_command(names: Iterable[str] = ()) -> str:
    """The exact command that fetches the given sets (all sets when empty)."""
    shorts = [OFFICIAL_SETS[n].short for n in names if n in OFFICIAL_SETS]
    suffix = f" --sets {' '.join(shorts)}" if shorts else ""
    return f"python -m unimal_envs.morphology fetch{suffix}"


def is_cached(name: str, cache: str | Path | None = None) -> bool:
    """Whether an official set is complete in the cache (its manifest is written last)."""
    return (cache_root(cache) / name / MANIFEST).is_file()


def official_set_dir(name: str, cache: str | Path | None = None) -> Path:
    """The cached folder of an official set.

    :param name: ``unimals100-train``, ``unimals100-test`` or ``unimals100-mutants``.
    :param cache: cache folder (default :func:`cache_root`).
    :raises MorphologyError: unknown name, or the set is not in the cache (the message gives the
        exact fetch command).
    """
    if name not in OFFICIAL_SETS:
        raise MorphologyError(f"unknown official set '{name}'; official sets are {list(OFFICIAL_SETS)}")
    folder = cache_root(cache) / name
    if not (folder / MANIFEST).is_file():
        raise MorphologyError(
            f"the official robot set '{name}' is not in the cache {cache_root(cache)}; fetch it once with: "
            f"{fetch_command([name])}  (set UNIMAL_DATA to use another cache folder)"
        )
    return folder
