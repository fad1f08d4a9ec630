"""The shipped morphology sets: how they are made from fixed seeds, and their statistics.

Two sets ship with the package, 100 robots each, in the unimals_100 layout
(``<set>/xml/<name>.xml`` + ``<set>/metadata/<name>.json``):

* ``train`` (``train-000`` ... ``train-099``): seeds 1_000_000, 1_000_001, ...
* ``novel`` (``novel-000`` ... ``novel-099``): seeds 2_000_000, 2_000_001, ... (held-out robots)

Robot ``i`` of a set is the ``i``-th seed of its range whose body plan
(:meth:`~unimal_envs.morphology.generator.UnimalGenome.signature`) is new to the set; seeds giving
a duplicate are skipped. Each file records its seed in its first comment, so any shipped robot can
be regenerated on its own (:func:`regenerate`).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from unimal_envs import contract as C
from unimal_envs.morphology.generator import LIMB_RADIUS, PROVENANCE_PREFIX, GeneratedUnimal, generate_unimal
from unimal_envs.morphology.loader import SHIPPED_SETS, _DATA_DIR, MorphologyError, load_morphology, morphology_files


@dataclass(frozen=True)
class SetSpec:
    """How a shipped set is generated.

    :param name: set name, also the robots' name prefix.
    :param first_seed: seed of the first candidate robot; later candidates use the next integers.
    :param size: number of robots.
    """

    name: str
    first_seed: int
    size: int = 100

    def robot_name(self, index: int) -> str:
        """``<set>-<index:03d>``, e.g. ``train-007``."""
        return f"{self.name}-{index:03d}"


#: The shipped sets; the seed ranges are far apart so the sets never share a seed.
SETS = {"train": SetSpec("train", 1_000_000), "novel": SetSpec("novel", 2_000_000)}
assert tuple(SETS) == SHIPPED_SETS

#: Where the shipped sets live inside the package.
DATA_DIR = _DATA_DIR

_SEED_RE = re.compile(re.escape(PROVENANCE_PREFIX) + r", seed=(\d+)(?:, num_limbs=(\d+))? -->")


def set_names(which: str) -> list[str]:
    """Expand a ``--set`` value (``train``, ``novel`` or ``all``) to set names.

    :param which: a set name or ``"all"``.
    """
    if which == "all":
        return list(SETS)
    if which not in SETS:
        raise MorphologyError(f"unknown morphology set '{which}'; choose from {[*SETS, 'all']}")
    return [which]


def generate_set(name: str, progress: bool = False) -> list[GeneratedUnimal]:
    """Generate a shipped set from its seeds (deterministic, byte-identical to the shipped files).

    :param name: ``train`` or ``novel``.
    :param progress: show a tqdm progress bar.
    """
    spec = SETS[set_names(name)[0]]
    robots: list[GeneratedUnimal] = []
    seen: set[str] = set()
    seed = spec.first_seed
    with tqdm(total=spec.size, desc=f"generating {spec.name}", unit="robot", disable=not progress) as bar:
        while len(robots) < spec.size:
            robot = generate_unimal(seed, name=spec.robot_name(len(robots)))
            signature = robot.genome.signature()
            if signature not in seen:
                seen.add(signature)
                robots.append(robot)
                bar.update()
            seed += 1
    return robots


def write_set(robots: Sequence[GeneratedUnimal], set_dir: str | Path, prefix: str) -> None:
    """Write robots in the unimals_100 layout, replacing earlier files of the same set.

    :param robots: the robots.
    :param set_dir: directory receiving ``xml/`` and ``metadata/``.
    :param prefix: set name; stale ``<prefix>-*`` files are removed first.
    """
    set_dir = Path(set_dir)
    for sub, ext in (("xml", "xml"), ("metadata", "json")):
        for stale in (set_dir / sub).glob(f"{prefix}-*.{ext}"):
            stale.unlink()
    for robot in robots:
        robot.write(set_dir)


def compare_set(robots: Sequence[GeneratedUnimal], set_dir: str | Path) -> list[str]:
    """Names of robots whose files in ``set_dir`` are missing or differ (byte-wise).

    :param robots: freshly generated robots.
    :param set_dir: directory holding ``xml/`` and ``metadata/``.
    """
    set_dir = Path(set_dir)
    bad = []
    for robot in robots:
        xml_path = set_dir / "xml" / f"{robot.name}.xml"
        meta_path = set_dir / "metadata" / f"{robot.name}.json"
        same = (
            xml_path.is_file()
            and meta_path.is_file()
            and xml_path.read_text() == robot.xml
            and meta_path.read_text() == robot.metadata_json
        )
        if not same:
            bad.append(robot.name)
    return bad


def seed_of(xml: str) -> tuple[int, int | None] | None:
    """The ``(seed, num_limbs)`` recorded in a generated robot file (``None`` if it has none).

    :param xml: MJCF text.
    """
    match = _SEED_RE.search(xml)
    if match is None:
        return None
    return int(match.group(1)), (int(match.group(2)) if match.group(2) else None)


def regenerate(path: str | Path) -> GeneratedUnimal:
    """Regenerate one generated robot file from the seed recorded in it.

    :param path: a file written by :func:`generate_unimal` (e.g. a shipped robot).
    :raises MorphologyError: the file records no seed (not a plain generated robot).
    """
    path = Path(path)
    recorded = seed_of(path.read_text())
    if recorded is None:
        raise MorphologyError(f"{path}: no generator seed recorded in the file (mutated or foreign robot?)")
    seed, num_limbs = recorded
    return generate_unimal(seed, num_limbs=num_limbs, name=path.stem)


# ------------------------------------------------------------------------------------ statistics
#: Statistics of :func:`collect_stats`; the last two are continuous (no histogram).
STATISTICS = ("limbs", "dof", "depth", "hinges per limb", "limb length h", "torso height")
_CONTINUOUS = {"torso height"}
# geom_size[1] (capsule half-length) inside the static body features: pos 3, ipos 3, iquat 4,
# geom_quat 4, mass 1, then geom_size 2.
_HALF_LENGTH_COLUMN = C.STATIC_BODY.start + 16


@dataclass
class SetStats:
    """Per-robot or per-limb values of each statistic for one set of robots.

    :param label: how the set is shown in tables.
    :param values: statistic name -> values.
    """

    label: str
    values: dict[str, list[float]] = field(default_factory=dict)

    def summary(self, stat: str) -> tuple[float, float, float]:
        """``(min, mean, max)`` of one statistic."""
        vals = self.values[stat]
        return min(vals), sum(vals) / len(vals), max(vals)

    def histogram(self, stat: str) -> str:
        """``value:count`` pairs in increasing value order (``-`` for continuous statistics)."""
        if stat in _CONTINUOUS:
            return "-"
        counts = Counter(self.values[stat])
        return " ".join(f"{_num(v)}:{n}" for v, n in sorted(counts.items()))


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def collect_stats(label: str, files: Iterable[str | Path]) -> SetStats:
    """Load robots through the loader and gather their statistics.

    :param label: table label of the set.
    :param files: robot MJCF files.
    """
    stats = SetStats(label, {stat: [] for stat in STATISTICS})
    for path in files:
        robot = load_morphology(path)
        stats.values["limbs"].append(robot.num_limbs)
        stats.values["dof"].append(robot.dof)
        stats.values["depth"].append(robot.depth)
        stats.values["torso height"].append(round(robot.torso_height, 2))
        for token, hinges in enumerate(robot.hinges[1:], start=1):
            stats.values["hinges per limb"].append(sum(h is not None for h in hinges))
            half_length = robot.proprio_static[token, _HALF_LENGTH_COLUMN]
            stats.values["limb length h"].append(round(2 * half_length - LIMB_RADIUS, 1))
    return stats


def set_stats(name: str, root: str | Path | None = None) -> SetStats:
    """Statistics of a shipped set (or of a copy under ``root``).

    :param name: ``train`` or ``novel``.
    :param root: directory holding ``<name>/xml``; default the package data.
    """
    base = Path(root) if root is not None else DATA_DIR
    return collect_stats(f"{name} ({base.name if root else 'shipped'})", morphology_files(base / name))


def stats_rows(sets: Sequence[SetStats]) -> list[list[str]]:
    """Table rows ``[statistic, set, n, min, mean, max, histogram]``, grouped by statistic.

    :param sets: the sets to show side by side.
    """
    rows = []
    for stat in STATISTICS:
        for s in sets:
            lo, mean, hi = s.summary(stat)
            rows.append([stat, s.label, str(len(s.values[stat])), _num(lo), f"{mean:.2f}", _num(hi), s.histogram(stat)])
    return rows


STATS_HEADER = ["statistic", "set", "n", "min", "mean", "max", "histogram (value:count)"]
