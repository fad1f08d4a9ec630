"""Where the official robot sets live on this machine, and whether they are there.

The names, the cache folder and the lookup of a fetched set; :mod:`unimal_envs.morphology.official`
fetches and verifies the sets, :mod:`unimal_envs.morphology.loader` resolves set names through
:func:`official_set_dir`. Nothing here reads a robot, so both can stand on it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
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
    :param count: the number of robots its folder in the archive holds.
    :param byte_copies: robots of the archive folder that are byte-for-byte copies of an official
        training robot (``{name: training robot}``). They are left out when the set is installed and
        when it is listed: a zero-shot figure on "held-out" robots must not contain training robots.
    """

    name: str
    short: str
    folder: str
    count: int
    byte_copies: dict[str, str] = field(default_factory=dict)

    @property
    def robots(self) -> int:
        """How many robots the installed set holds (the archive's, less the byte copies)."""
        return self.count - len(self.byte_copies)


#: The five robots of the official test folder whose MJCF file is the same bytes as a training
#: robot's: four under the training robot's own name, one under another name. The
#: fetch checks that exactly these are copies (SHA-256 against the shipped training checksums).
TEST_BYTE_COPIES = {
    "floor-5506-12-12-01-15-33-01": "floor-5506-12-12-01-15-33-01",
    "floor-5506-12-14-01-15-22-01": "floor-5506-12-14-01-15-22-01",
    "floor-5506-2-0-01-11-27-44": "floor-5506-12-12-01-15-33-01",
    "floor-5506-4-14-01-14-32-47": "floor-5506-4-14-01-14-32-47",
    "floor-5506-9-7-01-13-40-02": "floor-5506-9-7-01-13-40-02",
}


OFFICIAL_SETS = {
    s.name: s
    for s in (
        OfficialSet("unimals100-train", "train", "train", 100),
        OfficialSet("unimals100-test", "test", "test", 102, TEST_BYTE_COPIES),
        OfficialSet("unimals100-mutants", "mutants", "train_mutate_1000", 1000),
    )
}
SHORT_NAMES = {s.short: s for s in OFFICIAL_SETS.values()}

#: How many official training robots :data:`SUBSETS` hold out for validation.
VALIDATION_ROBOTS = 10


@dataclass(frozen=True)
class Subset:
    """A named part of an official set (no files of its own: it lists part of the parent's robots).

    :param name: the set name used everywhere a set name is accepted.
    :param parent: the official set it is taken from.
    :param validation: ``True`` for the held-out robots, ``False`` for the rest.
    """

    name: str
    parent: str
    validation: bool

    def select(self, files: list[Path]) -> list[Path]:
        """This subset of the parent's sorted robot files: the validation robots are
        :data:`VALIDATION_ROBOTS` spread evenly over the sorted list, its first and last included
        (robot names sort by family -- ``floor-*``, ``mvt-*``, ``vt-*`` -- so a spread takes every
        family, a prefix only one)."""
        n = len(files)
        held = {round(i * (n - 1) / (VALIDATION_ROBOTS - 1)) for i in range(VALIDATION_ROBOTS)} if n >= VALIDATION_ROBOTS else set()
        return [f for i, f in enumerate(files) if (i in held) == self.validation]


#: The official training robots split for choices about generalisation: settings are chosen by
#: training on ``unimals100-fit`` (90 robots) and measuring on ``unimals100-val`` (10 robots), never
#: on the held-out ``unimals100-test`` robots, which only report.
SUBSETS = {
    s.name: s
    for s in (
        Subset("unimals100-val", "unimals100-train", validation=True),
        Subset("unimals100-fit", "unimals100-train", validation=False),
    )
}


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
            f"{fetch_command([name])}  (without a network, from a copy of the robots: "
            f"python -m unimal_envs.morphology fetch --source PATH; set UNIMAL_DATA to use another cache folder)"
        )
    return folder
