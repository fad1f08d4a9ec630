"""Variations of any robot set: DERL's mutations applied to existing robots, official ones included.

MetaMorph reports zero-shot generalisation not only to new robots but to *variations* of its
training robots: the same robots with changed kinematics or dynamics. This module makes such sets
from any set of UNIMAL robots, reproducibly, with the mutation operators of DERL's design space
(:data:`~unimal_envs.morphology.generator.MUTATION_OPS`, as the generator applies them):

=============  ==========================================================================  =========
kind           operators                                                                   changes
=============  ==========================================================================  =========
``kinematic``  ``grow_limb``, ``delete_limb``, ``limb_params`` (a limb group's length),     the shape
               ``joint_angle`` (hinge ranges), ``dof`` (which hinges, their ranges, gears)
``dynamic``    ``density`` (limb and torso densities), ``gear`` (motor gears)              the masses
                                                                                           and torques
=============  ==========================================================================  =========

A robot file is read back into its design-space parameters (:func:`genome_from_xml`): torso and
limb densities, and per limb its parent and attachment site, length, direction (θ, φ), hinges
(axis, range, gear) and mirror pairing. The reading is checked, not trusted: every limb's body
position, capsule, sites and hinge anchor derived from the parameters must equal the file's, or the
robot is refused as outside the design space (:class:`~unimal_envs.morphology.errors.MorphologyError`).
The official robots read back exactly, except for one quirk the generator fixes: DERL leaves a
``btm_pos`` site at ``(r + h)·d`` after a ``limb_params`` mutation, so a variant's spawn height is
recomputed from its true capsule tips.

Every variant is **valid** (:func:`check_variant`): it loads through the environments' loader, it
stands (dropped on flat ground at zero torque its torso stays above half its standing height for
2 s) unless its parent did not either, and it lies **inside the official envelope** (spawn height
<= 1.05 m, at most 5 limb levels, at most 10 limbs: the range of the official training robots,
as the shipped sets use it; a parent already above it -- one official robot spawns at 1.07 m once
its ``btm_pos`` is at its true tip -- bounds its own variants instead). A draw that fails is drawn again (at most ``attempts`` times) with
the next seed of the variant's stream, so a variant never depends on others.

A **variation set** (:func:`make_variation_set`, ``unimal-morphologies mutate``) holds
``per_robot`` variants of each robot of a set, named ``<robot>-<kind>-<k>``; variant ``k`` of a
robot comes from ``np.random.default_rng([seed, robot index, k])``, so the same command gives the
same bytes. Its folder has the unimals_100 layout and a ``VARIATIONS.json`` naming, per variant,
its parent, operator and seed.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from unimal_envs.morphology.cache import cache_root
from unimal_envs.morphology.errors import MorphologyError
from unimal_envs.morphology.generator import (
    LIMB_HEIGHTS,
    LIMB_RADIUS,
    MAX_LIMBS,
    PHIS,
    THETAS,
    GeneratedUnimal,
    Hinge,
    Limb,
    UnimalGenome,
    _Probe,
    allowed_mutations,
    finalize,
    limb_layout,
    mutate_genome,
)
from unimal_envs.morphology.loader import TORSO, morphology_files, parse_morphology, read_metadata
from unimal_envs.morphology.sets import SETS, passive_standing_ratio

#: The operators of each kind of variation.
KINDS: dict[str, tuple[str, ...]] = {
    "kinematic": ("grow_limb", "delete_limb", "limb_params", "joint_angle", "dof"),
    "dynamic": ("density", "gear"),
}
#: The official envelope (the shipped sets' filters: the range of the official training robots).
MAX_TORSO_HEIGHT = SETS["train"].max_torso_height
MAX_DEPTH = SETS["train"].max_depth
#: A robot "stands" when its torso stays above this share of its standing height (FT's fall threshold).
STANDING_RATIO = 0.5
#: The record of a variation set, next to its ``xml/`` and ``metadata/`` folders.
RECORD = "VARIATIONS.json"
_TOLERANCE = 1e-6


# ------------------------------------------------------------------------------ reading a robot
def _floats(text: str | None) -> list[float]:
    return [float(v) for v in (text or "").split()]


def _snap(value: float, grid: Sequence[float], what: str, source: str, tolerance: float) -> float:
    best = min(grid, key=lambda g: abs(g - value))
    if abs(best - value) > tolerance:
        raise MorphologyError(f"{source}: {what} {value:.4f} is not in the design space {list(grid)}")
    return best


def genome_from_xml(xml: str, source: str = "robot", symmetric_limbs: Sequence[Sequence[int]] | None = None) -> UnimalGenome:
    """The design-space parameters of a UNIMAL robot file (see the module docstring).

    :param xml: the robot's MJCF text (unimals_100 layout, official or generated).
    :param source: how errors name the robot.
    :param symmetric_limbs: the metadata's mirrored pairs ``[[k, k+1], ...]``; default: read from the
        limbs' mirror sites (pairs of consecutive limb numbers).
    :raises MorphologyError: the file is not a robot of DERL's design space, or its parameters do not
        reproduce its geometry.
    """
    root = ET.fromstring(xml)
    torso = root.find(f".//worldbody/body[@name='{TORSO}']")
    if torso is None:
        raise MorphologyError(f"{source}: no body named '{TORSO}'")
    torso_geom = torso.find("geom")
    modes = [s.get("name", "").split("/")[1] for s in torso.findall("site") if s.get("class") == "torso_growth_site"]
    gears = {m.get("joint"): int(round(float(m.get("gear", "0")))) for m in root.iter("motor")}
    limb_densities: set[int] = set()
    genome = UnimalGenome(
        torso_density=int(round(float(torso_geom.get("density", "1000")))) if torso_geom is not None else 1000,
        limb_density=0,
        torso_mode=modes[0] if modes else "horizontal_y",
    )
    bodies: list[tuple[ET.Element, int | None]] = [(child, None) for child in torso.findall("body")]
    while bodies:
        body, parent = bodies.pop(0)
        name = body.get("name", "")
        if not name.startswith("limb/"):
            raise MorphologyError(f"{source}: body {name!r} is not a UNIMAL limb (limb/<k>)")
        idx = int(name.split("/")[1])
        geom = body.find("geom")
        fromto = _floats(geom.get("fromto") if geom is not None else None)
        if len(fromto) != 6 or any(abs(v) > _TOLERANCE for v in fromto[:3]):
            raise MorphologyError(f"{source}: limb {idx} has no capsule from its body origin")
        tip = np.array(fromto[3:])
        length = float(np.linalg.norm(tip))
        h = _snap(length - LIMB_RADIUS, LIMB_HEIGHTS, f"limb {idx} length", source, 0.02)
        phi = _snap(math.degrees(math.acos(max(-1.0, min(1.0, tip[2] / length)))), PHIS, f"limb {idx} polar angle", source, 3.0)
        theta = 0 if phi == 180 else _snap(math.degrees(math.atan2(tip[1], tip[0])) % 360 % 360, (*THETAS, 360), "azimuth", source, 3.0)
        theta = int(theta) % 360
        limb_densities.add(int(round(float(geom.get("density", "1000")))))  # type: ignore[union-attr]
        hinges = []
        for joint in body.findall("joint"):
            joint_name = joint.get("name", "")
            axis = joint_name.split("/")[0].removeprefix("limb")
            if axis not in ("x", "y") or joint_name not in gears:
                raise MorphologyError(f"{source}: joint {joint_name!r} is not a motorised limbx/limby hinge")
            low, high = (int(round(v)) for v in _floats(joint.get("range")))
            hinges.append(Hinge(axis, (low, high), gears[joint_name]))
        hinges.sort(key=lambda hinge: hinge.axis)
        mid = body.find(f"site[@name='limb/mid/{idx}']")
        mirrored = mid is not None and mid.get("class") == "mirror_growth_site"
        position = np.array(_floats(body.get("pos")))
        site = "torso"
        if parent is not None:
            # the attachment site: the parent's mid or btm site, whichever reproduces the body position
            site = "btm"
            for kind in ("mid", "btm"):
                trial = Limb(idx, parent, kind, h, theta, int(phi), tuple(hinges), mirrored)
                genome.limbs[idx] = trial
                if np.allclose(limb_layout(genome, trial).pos, position, atol=_TOLERANCE):
                    site = kind
                    break
        genome.limbs[idx] = Limb(idx, parent, site, h, theta, int(phi), tuple(hinges), mirrored)
        bodies += [(child, idx) for child in body.findall("body")]
    if len(limb_densities) != 1:
        raise MorphologyError(f"{source}: limbs of different densities {sorted(limb_densities)} (the design space shares one)")
    genome.limb_density = limb_densities.pop()
    genome.limbs = dict(sorted(genome.limbs.items()))
    pairs = [tuple(p) for p in symmetric_limbs] if symmetric_limbs is not None else _mirror_pairs(genome)
    paired = {idx for pair in pairs for idx in pair}
    genome.groups = sorted([*(tuple(int(i) for i in p) for p in pairs), *((k,) for k in genome.limbs if k not in paired)])
    genome.next_idx = max(genome.limbs, default=-1) + 1
    _check_layout(genome, torso, source)
    # what touches now was allowed when it grew: a later growth must only avoid new contacts
    genome.allowed_pairs = _Probe.of(genome).contacts()
    return genome


def _mirror_pairs(genome: UnimalGenome) -> list[tuple[int, int]]:
    mirrored = [k for k, limb in genome.limbs.items() if limb.mirrored]
    return [(a, b) for a, b in zip(mirrored[::2], mirrored[1::2])]


def _check_layout(genome: UnimalGenome, torso: ET.Element, source: str) -> None:
    """Every limb's derived coordinates equal the file's (``btm_pos`` aside: DERL's quirk)."""
    for body in torso.iter("body"):
        if body is torso:
            continue
        idx = int(body.get("name", "").split("/")[1])
        lay = limb_layout(genome, genome.limbs[idx])
        found = {
            "body position": (_floats(body.get("pos")), lay.pos),
            "capsule": (_floats(body.find("geom").get("fromto"))[3:], lay.tip),  # type: ignore[union-attr]
            "mid site": (_floats(body.find(f"site[@name='limb/mid/{idx}']").get("pos")), lay.mid),  # type: ignore[union-attr]
            "btm site": (_floats(body.find(f"site[@name='limb/btm/{idx}']").get("pos")), lay.btm),  # type: ignore[union-attr]
        }
        for joint in body.findall("joint"):
            found[f"hinge anchor {joint.get('name')}"] = (_floats(joint.get("pos")), lay.joint_pos)
        for what, (in_file, derived) in found.items():
            if len(in_file) != 3 or not np.allclose(in_file, derived, atol=_TOLERANCE):
                raise MorphologyError(f"{source}: limb {idx}'s {what} {in_file} is not the design space's {list(derived)}")


def read_genome(path: str | Path) -> UnimalGenome:
    """:func:`genome_from_xml` of a robot file, with the mirror pairs of its metadata when it has one."""
    path = Path(path)
    metadata = read_metadata(path)
    pairs = metadata.get("symmetric_limbs") if metadata else None
    return genome_from_xml(path.read_text(), source=str(path), symmetric_limbs=pairs)


# ------------------------------------------------------------------------------------- variants
@dataclass(frozen=True)
class Check:
    """The validity of one variant (see the module docstring)."""

    loads: bool
    stands: bool
    inside_envelope: bool
    problem: str = ""

    @property
    def valid(self) -> bool:
        return self.loads and self.stands and self.inside_envelope


def stands(xml: str) -> bool:
    """Whether a robot stays up at zero torque for 2 s on flat ground (FT's fall threshold)."""
    return passive_standing_ratio(xml) > STANDING_RATIO


def check_variant(robot: GeneratedUnimal, parent: GeneratedUnimal | None = None, parent_stands: bool = True) -> Check:
    """Whether a variant loads, stands (when its parent does) and lies inside the official envelope.

    :param robot: the variant.
    :param parent: its parent robot as the generator writes it: a parent already above the envelope
        (one official robot spawns at 1.07 m once its ``btm_pos`` quirk is fixed) widens it to its own
        height and depth, so that a dynamic variant is never refused for its parent's shape.
    :param parent_stands: whether its parent robot stands; a parent that falls at zero torque (a
        third of the official training robots do) does not make its variants fail.
    """
    try:
        parse_morphology(robot.xml, robot.name)
    except MorphologyError as err:
        return Check(False, False, False, f"does not load: {err}")
    depth = robot.genome.depth()
    max_height = max(MAX_TORSO_HEIGHT, parent.torso_height if parent is not None else 0.0)
    max_depth = max(MAX_DEPTH, parent.genome.depth() if parent is not None else 0)
    inside = robot.torso_height <= max_height + _TOLERANCE and depth <= max_depth and robot.genome.num_limbs <= MAX_LIMBS
    if not inside:
        return Check(True, False, False, f"outside the envelope: spawn height {robot.torso_height} m, depth {depth}")
    if parent_stands and not stands(robot.xml):
        return Check(True, False, True, "falls at zero torque where its parent stands")
    return Check(True, True, True)


def vary(
    path: str | Path, kind: str, seed: Sequence[int] | int, name: str, attempts: int = 20, genome: UnimalGenome | None = None
) -> tuple[GeneratedUnimal, str]:
    """One valid variant of a robot: a random operator of ``kind``, drawn again until the variant is
    valid and differs from the robot.

    :param path: the robot file.
    :param kind: ``kinematic`` or ``dynamic`` (:data:`KINDS`).
    :param seed: the seed (or seed sequence) of the variant's random stream.
    :param name: the variant's name.
    :param attempts: draws before giving up.
    :param genome: the robot's parameters, if already read (:func:`read_genome`).
    :returns: the variant and the operator that made it.
    :raises MorphologyError: an unknown kind, a robot outside the design space, or no valid variant
        in ``attempts`` draws.
    """
    if kind not in KINDS:
        raise MorphologyError(f"unknown kind of variation {kind!r}; choose from {list(KINDS)}")
    parent = read_genome(path) if genome is None else genome
    parent_stands = stands(Path(path).read_text())
    rewritten = finalize(parent, Path(path).stem, "the parent, as the generator writes it")
    rng = np.random.default_rng(seed)
    problems = []
    for _ in range(attempts):
        ops = [op for op in KINDS[kind] if op in allowed_mutations(parent)]
        op = ops[int(rng.integers(len(ops)))]
        child, _ = mutate_genome(parent, rng, op)
        if child is parent or (
            child.limbs == parent.limbs and child.limb_density == parent.limb_density and child.torso_density == parent.torso_density
        ):
            problems.append(f"{op}: no change")
            continue
        robot = finalize(child, name, f"{kind} variation ({op}) of {Path(path).stem}, seed={list(np.atleast_1d(seed))}")
        check = check_variant(robot, rewritten, parent_stands)
        if check.valid:
            return robot, op
        problems.append(f"{op}: {check.problem}")
    raise MorphologyError(f"{Path(path).stem}: no valid {kind} variant in {attempts} draws ({'; '.join(problems[-3:])})")


def default_folder(robots: str | Path, kind: str, seed: int) -> Path:
    """Where ``unimal-morphologies mutate`` writes a set without ``--out``: its name,
    ``<robots>-<kind>-s<seed>``, in the cache's ``variations/`` folder (``$UNIMAL_DATA``)."""
    return cache_root() / "variations" / f"{Path(str(robots)).name}-{kind}-s{seed}"


def make_variation_set(
    robots: str | Path | Sequence[str | Path],
    kind: str,
    out: str | Path,
    per_robot: int = 1,
    seed: int = 0,
    progress: bool = True,
) -> list[Path]:
    """Write a variation set: ``per_robot`` valid variants of every robot (see the module docstring).

    :param robots: a set name (``unimals100-train``, ``train``...), a folder or a list of files.
    :param kind: ``kinematic`` or ``dynamic``.
    :param out: the set's folder (``xml/``, ``metadata/``, ``VARIATIONS.json``); written whole,
        ``VARIATIONS.json`` last.
    :param per_robot: variants per robot.
    :param seed: the set's seed.
    :param progress: show a bar over the robots.
    :returns: the variants' MJCF files.
    :raises MorphologyError: see :func:`vary`; ``per_robot`` < 1.
    """
    if per_robot < 1:
        raise MorphologyError(f"per_robot must be at least 1, got {per_robot}")
    if kind not in KINDS:
        raise MorphologyError(f"unknown kind of variation {kind!r}; choose from {list(KINDS)}")
    files = morphology_files(robots)
    out = Path(out)
    (out / RECORD).unlink(missing_ok=True)  # an unfinished set has no record
    record: dict[str, object] = {"source": str(robots), "kind": kind, "operators": list(KINDS[kind]), "seed": seed, "per_robot": per_robot}
    variants: dict[str, dict[str, object]] = {}
    written = []
    for index, path in enumerate(tqdm(files, desc=f"{kind} variants", unit="robot", disable=not progress)):
        genome = read_genome(path)
        for k in range(per_robot):
            name = f"{path.stem}-{kind}-{k}"
            robot, op = vary(path, kind, [seed, index, k], name, genome=genome)
            written.append(robot.write(out)[0])
            variants[name] = {"parent": path.stem, "operator": op, "seed": [seed, index, k]}
    record["variants"] = variants
    (out / RECORD).write_text(json.dumps(record, indent=1) + "\n")
    return written
