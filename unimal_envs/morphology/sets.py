"""The shipped morphology sets: how they are made from fixed seeds, and their statistics.

Two sets ship with the package, 100 robots each, in the unimals_100 layout
(``<set>/xml/<name>.xml`` + ``<set>/metadata/<name>.json``):

* ``train`` (``train-000`` ... ``train-099``): seeds 1_000_000, 1_000_001, ...
* ``novel`` (``novel-000`` ... ``novel-099``): seeds 2_000_000, 2_000_001, ... (held-out robots)

Robot ``i`` of a set is made by the ``i``-th seed of its range that passes three set-level
filters; the other seeds are skipped:

* **No duplicates:** its body plan (:func:`plan_signature`: the body tree with every limb's
  position and capsule, ignoring joints and densities) is new to the set, and for ``novel`` also
  absent from ``train``, in the spirit of DERL's deduplicated initial population.
* **Inside the official envelope:** spawn height <= 1.05 m and at most 5 limb levels, the range of
  the official unimals_100 train set (0.30-1.04 m, depth 2-5). The raw design space also yields
  stilt-like robots up to ~2.5 m tall and 7 levels deep (about half of all seeds); the official
  robots, selected by evolution for locomotion, contain none.
* **Stands on its own** (optional, on for the shipped sets, off by default for new sets): dropped
  on flat ground with the environments' contact settings (``filterparent`` on, no excludes) and
  zero control, the torso stays above half its standing height (the FT fall threshold) for 2 s.
  Most official train robots pass this test, but few generated robots inside the envelope do.
  The shipped sets keep it so that few episodes end at once; the price is a set that never falls
  at zero torque, unlike the official one. ``generate --stand-filter 0 --out DIR`` makes sets without it.

The filters play the part of DERL's selection: they keep the sets comparable to the official one
(see ``unimal-morphologies stats --compare``). Only the standing test depends on simulated dynamics;
a different MuJoCo version could flip a borderline robot, which ``generate --check`` reports. Every
shipped file is still exactly ``generate_unimal(seed)`` for the seed recorded in it.

Each file records its seed in its first comment, so any shipped robot can be regenerated on its own
(:func:`regenerate`).
"""

from __future__ import annotations

import collections
import itertools
import math
import re
import xml.etree.ElementTree as ET
from collections import Counter
from collections.abc import Generator, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
from tqdm.auto import tqdm

from unimal_envs import contract as C
from unimal_envs.morphology.generator import (
    LIMB_RADIUS,
    PROVENANCE_PREFIX,
    GeneratedUnimal,
    finalize,
    generate_unimal,
    seed_provenance,
)
from unimal_envs.morphology.loader import (
    FLOOR_OFFSET,
    SHIPPED_SETS,
    TORSO,
    MorphologyError,
    load_morphology,
    morphology_files,
    shipped_set_dir,
)


@dataclass(frozen=True)
class SetSpec:
    """How a shipped set is generated.

    :param name: set name, also the robots' name prefix.
    :param first_seed: seed of the first candidate robot; later candidates use the next integers.
    :param size: number of robots.
    :param max_torso_height: robots spawning higher are skipped.
    :param max_depth: robots with more limb levels are skipped.
    :param min_standing_ratio: robots whose torso sinks below this fraction of their standing height
        in :func:`passive_standing_ratio` are skipped (``0``, the default for new sets, disables it).
    :param disjoint_from: sets whose body plans this set must not repeat.
    """

    name: str
    first_seed: int
    size: int = 100
    max_torso_height: float = 1.05
    max_depth: int = 5
    min_standing_ratio: float = 0.0
    disjoint_from: tuple[str, ...] = ()

    def admits(self, robot: GeneratedUnimal) -> bool:
        """Whether a robot passes the set-level filters (height, depth, standing; cheapest first)."""
        if robot.torso_height > self.max_torso_height or robot.genome.depth() > self.max_depth:
            return False
        return self.min_standing_ratio <= 0 or passive_standing_ratio(robot.xml) > self.min_standing_ratio

    def robot_name(self, index: int) -> str:
        """``<set>-<index:03d>``, e.g. ``train-007``."""
        return f"{self.name}-{index:03d}"


#: The shipped sets; the seed ranges are far apart so the sets never share a seed.
SETS = {
    "train": SetSpec("train", 1_000_000, min_standing_ratio=0.5),
    "novel": SetSpec("novel", 2_000_000, min_standing_ratio=0.5, disjoint_from=("train",)),
}
assert tuple(SETS) == SHIPPED_SETS

#: Where the shipped sets live inside the package.
DATA_DIR = shipped_set_dir("train").parent

_SEED_RE = re.compile(re.escape(PROVENANCE_PREFIX) + r", seed=(\d+)(?:, num_limbs=(\d+))? -->")


def plan_signature(xml: str) -> str:
    """Canonical text of a robot's body plan: the body tree with each body's position and geom.

    Joints, gears and densities are ignored and siblings are sorted, so two files share a
    signature exactly when they hold the same rigid shape.

    :param xml: robot MJCF text.
    """

    def node(body: ET.Element) -> str:
        geom = body.find("geom")
        label = f"{body.get('pos')}|{geom.get('fromto') or geom.get('size')}" if geom is not None else str(body.get("pos"))
        return label + "[" + ",".join(sorted(node(kid) for kid in body.findall("body"))) + "]"

    torso = ET.fromstring(xml).find(f".//body[@name='{TORSO}']")
    if torso is None:
        raise MorphologyError(f"no body named '{TORSO}'")
    return "[" + ",".join(sorted(node(kid) for kid in torso.findall("body"))) + "]"


def passive_standing_ratio(xml: str, seconds: float = 2.0) -> float:
    """Lowest torso height over ``seconds`` without control on flat ground, over the standing height.

    Uses the environments' contact settings: ``filterparent`` enabled and the file's excludes
    dropped; the ground is a plane at z = 0 and the standing height is ``torso z - 0.2``.

    :param xml: robot MJCF text.
    :param seconds: simulated time.
    """
    spec = mujoco.MjSpec.from_string(xml)
    spec.option.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    for exclude in list(spec.excludes):
        spec.delete(exclude)
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[20, 20, 1])
    model = spec.compile()
    data = mujoco.MjData(model)
    start = float(data.qpos[2])
    lowest = start
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        lowest = min(lowest, float(data.qpos[2]))
    return lowest / (start - FLOOR_OFFSET)


def set_names(which: str) -> list[str]:
    """Expand a ``--set`` value (``train``, ``novel`` or ``all``) to set names.

    :param which: a set name or ``"all"``.
    """
    if which == "all":
        return list(SETS)
    if which not in SETS:
        raise MorphologyError(f"unknown morphology set '{which}'; choose from {[*SETS, 'all']}")
    return [which]


@dataclass(frozen=True)
class _Candidate:
    """One seed's robot and whether it passed the order-independent filters."""

    seed: int
    robot: GeneratedUnimal
    admitted: bool


def _evaluate(seed: int, spec: SetSpec) -> _Candidate:
    """Generate and filter one candidate (runs in worker processes; depends on the seed only)."""
    robot = generate_unimal(seed, name=f"{spec.name}-candidate")
    return _Candidate(seed, robot, spec.admits(robot))


def _candidates(spec: SetSpec, jobs: int) -> Generator[_Candidate, None, None]:
    """Candidates of a set in seed order, evaluated by ``jobs`` processes ahead of consumption."""
    seeds = itertools.count(spec.first_seed)
    if jobs <= 1:
        yield from (_evaluate(seed, spec) for seed in seeds)
        return
    batch = 8 * jobs
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        pending: collections.deque = collections.deque()
        try:
            while True:
                while len(pending) < 2 * batch:
                    pending.append(pool.submit(_evaluate, next(seeds), spec))
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


def generate_set(
    name: str,
    progress: bool = False,
    count: int | None = None,
    jobs: int = 1,
    exclude: Iterable[str] | None = None,
    spec: SetSpec | None = None,
) -> list[GeneratedUnimal]:
    """Generate a shipped set from its seeds (deterministic, byte-identical to the shipped files).

    :param name: ``train`` or ``novel``.
    :param progress: show a tqdm progress bar.
    :param count: generate only the first ``count`` robots (identical to the full set's first ones).
    :param jobs: worker processes generating candidates; the result does not depend on it.
    :param exclude: :func:`plan_signature` values of the sets this one must be disjoint from. Default:
        computed by generating those sets first (for ``novel``: the whole ``train`` set).
    :param spec: generate with this spec instead of the shipped one (e.g. without the standing filter).
    """
    spec = spec or SETS[set_names(name)[0]]
    size = spec.size if count is None else min(count, spec.size)
    if exclude is None:
        exclude = [plan_signature(r.xml) for other in spec.disjoint_from for r in generate_set(other, jobs=jobs)]
    robots: list[GeneratedUnimal] = []
    seen: set[str] = set(exclude)
    with tqdm(total=size, desc=f"generating {spec.name}", unit="robot", disable=not progress) as bar:
        candidates = _candidates(spec, jobs)
        while len(robots) < size:
            candidate = next(candidates)
            signature = plan_signature(candidate.robot.xml)
            if candidate.admitted and signature not in seen:
                seen.add(signature)
                # Rename: the file is then exactly generate_unimal(seed, name=...).
                genome, index = candidate.robot.genome, len(robots)
                robots.append(finalize(genome, spec.robot_name(index), seed_provenance(candidate.seed)))
                bar.update()
        candidates.close()
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
#: Statistics of :func:`collect_stats`.
STATISTICS = (
    "limbs", "dof", "depth", "hinges per limb", "limb length h", "torso height",
    "horizontal limbs", "mass (kg)", "falls at zero torque",
)  # fmt: skip
#: Continuous statistics are histogrammed in bins of this width (label = lower edge).
_BIN_WIDTH = {"torso height": 0.1, "mass (kg)": 5.0}
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
        """``value:count`` pairs in increasing value order (binned for continuous statistics)."""
        width = _BIN_WIDTH.get(stat)
        values = self.values[stat]
        if width is not None:
            values = [round(math.floor(v / width + 1e-9) * width, 6) for v in values]
        counts = Counter(values)
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
        model = robot.spec().compile()
        stats.values["mass (kg)"].append(round(float(model.body_mass.sum()), 1))
        # 1 = the robot falls (FT's threshold) within 2 s at zero torque on flat ground.
        stats.values["falls at zero torque"].append(int(passive_standing_ratio(robot.xml) <= 0.5))
        for token, hinges in enumerate(robot.hinges[1:], start=1):
            stats.values["hinges per limb"].append(sum(h is not None for h in hinges))
            half_length = robot.proprio_static[token, _HALF_LENGTH_COLUMN]
            stats.values["limb length h"].append(round(2 * half_length - LIMB_RADIUS, 1))
            body = model.body(robot.tokens[token]).id
            axis = model.geom_quat[model.body_geomadr[body]]
            # Horizontal limb: its capsule axis (the geom frame's z) has no vertical component.
            zx = 2 * (axis[1] * axis[3] + axis[0] * axis[2])
            zy = 2 * (axis[2] * axis[3] - axis[0] * axis[1])
            zz = 1 - 2 * (axis[1] ** 2 + axis[2] ** 2)
            stats.values["horizontal limbs"].append(int(abs(zz) < 1e-3 and math.hypot(zx, zy) > 0.99))
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


STATS_HEADER = ["statistic", "set", "n", "min", "mean", "max", "histogram (value:count; heights in 0.1 m, masses in 5 kg bins)"]


def stats_markdown(sets: Sequence[SetStats], command: str) -> str:
    """The statistics table as markdown, with the command that produced it.

    :param sets: the sets side by side.
    :param command: how the table was made (printed above it).
    """
    lines = [
        "# UNIMAL robot sets side by side",
        "",
        f"Made by `{command}`. Per robot (limbs, dof, depth, torso height = spawn height above the",
        "ground, mass, falls at zero torque = the torso sinks to half its standing height within 2 s",
        "without control on flat ground, `filterparent` on, no excludes) or per limb (hinges, length h,",
        "horizontal = capsule axis in the ground plane). The mean of a 0/1 statistic is a fraction.",
        "",
        "| " + " | ".join(STATS_HEADER) + " |",
        "|" + "---|" * len(STATS_HEADER),
    ]
    lines += ["| " + " | ".join(row) + " |" for row in stats_rows(sets)]
    return "\n".join(lines) + "\n"
