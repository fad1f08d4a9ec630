"""Procedural generator of UNIMAL robots: DERL's symmetric design space, rebuilt on ``mujoco.MjSpec``.

A UNIMAL is a spherical torso (radius 0.1) with a tree of capsule limbs (radius 0.05), each driven
by one or two motorised hinges, mirror-symmetric about the xz-plane. This module grows such robots
the way DERL's ``SymmetricUnimal`` does (spec §1.2-§1.6) and writes them in the unimals_100 file
layout, merged into our own template ``unimal_envs/assets/unimal_template.xml``.

Design space (spec §1.3), every choice uniform:

* limb direction: θ ∈ {0, 45, ..., 315}°, φ ∈ {90, 135, 180}° (horizontal to straight down),
  limb length h ∈ {0.2, 0.3, 0.4};
* hinges per limb: "x", "y" or "xy" (the x / y axis of the capsule frame), each with one of
  13 joint ranges and a motor gear in {150, 200, 250, 300};
* one shared limb density and a torso density, each in {500, 600, ..., 1000};
* at most 10 limbs.

Algorithm. A robot is a :class:`UnimalGenome` (the parameters, not the XML). A new robot starts as
a torso, grows a limb, then receives random mutations (uniform over :data:`MUTATION_OPS`, restricted
as in DERL: no ``grow_limb`` at 10 limbs, no ``delete_limb`` at <= 2 limbs) until it has at least
the target number of limbs. ``grow_limb`` makes up to 50 attempts; each picks a growth site
uniformly among all sites of the tree, 1 or 2 limbs for a plain ``growth_site`` and always a
mirrored pair for a ``mirror_growth_site``, samples the limb parameters once for the group, then
builds the candidate with :func:`build_spec`, compiles it and runs ``mj_forward`` at ``qpos0``
(no floor, ``filterparent`` disabled). The candidate is kept only if it is symmetric
(``|subtree_com[torso].y| < 1e-6``) and every contact is an allowed pair: parent/child, the two
members of a pair grown on the same site, or a pair allowed earlier. ``mj_forward`` at ``qpos0``
sees exactly the contacts and centre of mass that DERL's single ``sim.step()`` saw, since the step
computes both before integrating.

Saving (:func:`finalize`): motors in joint (document) order, sensors as in spec §1.4, hinge axes
read from the compiled capsule frames (columns 0/1 of ``geom_xmat``, 4 decimals), the torso placed
at ``z = -min z(btm_pos sites) + 0.2`` (2 decimals), and the contacts still active with
``filterparent`` enabled written as ``<exclude>`` pairs (environments drop them, spec §1.5).

Determinism. All randomness comes from one ``np.random.default_rng(seed)`` per call, drawn only
through ``Generator.integers``; the XML text is written by :func:`write_xml` with fixed float
formatting (coordinates 2 decimals, axes 4 decimals, ``-0`` printed as ``0``), never by
``MjSpec.to_xml``, so a seed always gives the same bytes for a given NumPy/MuJoCo pair.

Decisions on the spec's quirks and gaps
---------------------------------------
* **btm_pos after limb_params: fixed.** DERL rewrites ``limb/btm_pos/k`` to ``(r+h)·d`` instead of
  ``(2r+h)·d`` after a ``limb_params`` mutation (a substring test matches "btm" first). Here every
  ``btm_pos`` site is always at the capsule's true tip, ``(2r+h)·d``, so the spawn height never
  depends on the mutation history.
* **Symmetry test: tolerance, not equality.** DERL accepts only ``com_y == 0.0`` exactly; we accept
  ``|com_y| < 1e-6``. Coordinates are rounded to 2 decimals and mirrored exactly, so a symmetric
  robot gives 0 (up to summation order) and an asymmetric one is off by at least ~1e-4 m
  (measured); the tolerance only removes the dependence on floating-point summation order.
* **Touching means within 1e-6 m.** The acceptance test and the exclude list use a contact margin
  of 1e-6 m. On the 2-decimal grid many capsules are exactly tangent (e.g. a mirrored pair grown
  side by side), where MuJoCo's signed distance is ~±1e-17; the margin decides those cases the same
  way on every platform (tangent = touching).
* **Mirror-site canonicalisation:** growing on either member of a mirror pair of sites always
  starts from the member of the lower-numbered limb (DERL compares site names as strings). The
  first member of every limb pair is therefore on the +y side.
* **Folded limbs rejected (addition).** A child pointing exactly back along its parent's axis lies
  inside the parent capsule; DERL's contact test allows it (parent/child contacts are allowed).
  We reject it like the same-direction child on a ``mid`` site. The official train set has none.
* **limb_params keeps the robot valid (addition).** DERL changes a limb's length without testing
  the result; we test the changed robot like a grown one (symmetry and contacts) and retry up to
  50 times, always with a length different from the current one, and otherwise leave the robot
  unchanged.
* **Limb-count target:** uniform over {5, ..., 10}, as in MetaMorph's procedural ``random_100`` /
  ``random_1000`` sets (MX generator, spec §1.6). The growth loop stops at the first robot with at
  least the target, so a final pair can end one above it (never above 10). The official
  (evolved) train set spans 4-10 limbs with mode 8; DERL's initial populations (target 2-8) are
  smaller than what the benchmark trains on.

The generator itself never filters finished robots; the shipped sets add set-level filters
(duplicates, height, depth, standing), see :mod:`unimal_envs.morphology.sets`.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from unimal_envs.morphology.loader import FLOOR_OFFSET, TORSO, Morphology, parse_morphology

TEMPLATE_PATH = Path(__file__).resolve().parent.parent / "assets" / "unimal_template.xml"

LIMB_RADIUS = 0.05
TORSO_RADIUS = 0.1
#: Limb "height": capsule length between the end caps (total length 2r + h).
LIMB_HEIGHTS = (0.2, 0.3, 0.4)
THETAS = tuple(range(0, 360, 45))
PHIS = (90, 135, 180)
JOINT_AXES = ("x", "y", "xy")
#: The 13 joint ranges of the design space (degrees).
JOINT_RANGES = (
    (-30, 0), (0, 30), (-30, 30), (-45, 45), (-45, 0), (0, 45), (-60, 0),
    (0, 60), (-60, 60), (-90, 0), (0, 90), (-60, 30), (-30, 60),
)  # fmt: skip
GEARS = (150, 200, 250, 300)
DENSITIES = tuple(range(500, 1001, 100))
TORSO_MODES = ("horizontal_y", "vertical")
MAX_LIMBS = 10
#: Limb-count targets of new robots (MetaMorph's procedural sets; see module docstring).
TARGET_LIMBS = tuple(range(5, 11))
GROW_ATTEMPTS = 50
SYMMETRY_TOLERANCE = 1e-6
#: Geoms closer than this count as touching in the acceptance test (see module docstring).
CONTACT_MARGIN = 1e-6
MUTATION_OPS = ("grow_limb", "joint_angle", "gear", "dof", "limb_params", "density", "delete_limb")
#: Safety nets of the growth loop (reaching the target takes ~50 mutations, rarely a few hundred).
MAX_MUTATIONS = 2000
MAX_RESTARTS = 20

_FILTERPARENT = int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
Vec3 = tuple[float, float, float]


# --------------------------------------------------------------------------------------- geometry
def _clean(x: float, decimals: int) -> float:
    """Round and turn -0.0 into 0.0, so that mirrored values print identically."""
    return round(x, decimals) + 0.0


@lru_cache(maxsize=4096)
def sph2cart(rho: float, theta: float, phi: float) -> Vec3:
    """Point at distance ``rho`` in direction (θ, φ) (**radians**), rounded to 2 decimals (DERL's grid).

    DERL computes these with NumPy floats, so ``round(x, 2)`` is NumPy's rounding (scale by 100,
    round half to even, scale back), not Python's correctly rounded decimal ``round``; and it keeps
    angles in radians, a mirror image at ``2π - θ``. On the 45° grid the two differ exactly where a
    coordinate is a tie, ``ρ/2`` for the diagonal downward directions (θ ∈ {45, 135, 225, 315}°,
    φ = 135°): there a mirrored pair rounds asymmetrically in DERL (e.g. ``(-0.22, 0.23)`` against
    ``(-0.23, -0.22)``) and the symmetry test rejects it, which is why no official robot has such a
    limb. The same arithmetic here rejects them the same way.

    :param rho: distance from the origin.
    :param theta: azimuth in radians, from +x towards +y.
    :param phi: polar angle in radians from +z (π/2 = horizontal, π = straight down).
    """
    return (
        _np_round2(rho * math.sin(phi) * math.cos(theta)),
        _np_round2(rho * math.sin(phi) * math.sin(theta)),
        _np_round2(rho * math.cos(phi)),
    )


def _np_round2(x: float) -> float:
    """NumPy's ``round(x, 2)`` (``rint(x * 100) / 100``), with -0.0 turned into 0.0."""
    return float(np.rint(x * 100.0) / 100.0) + 0.0


def _add(a: Sequence[float], b: Sequence[float]) -> Vec3:
    return (_clean(a[0] + b[0], 2), _clean(a[1] + b[1], 2), _clean(a[2] + b[2], 2))


def _neg(a: Vec3) -> Vec3:
    return (_clean(-a[0], 2), _clean(-a[1], 2), _clean(-a[2], 2))


# ------------------------------------------------------------------------------------- the genome
@dataclass(frozen=True)
class Hinge:
    """One motorised hinge of a limb.

    :param axis: ``"x"`` or ``"y"``: which axis of the capsule frame it rotates about.
    :param range: joint range in degrees.
    :param gear: motor gear (maximum torque in N·m).
    """

    axis: str
    range: tuple[int, int]
    gear: int


@dataclass(frozen=True)
class Limb:
    """One capsule limb, described by its parameters (positions are derived, see :func:`limb_layout`).

    :param idx: limb number ``k`` (names ``limb/k``, ``limbx/k``, ...); never reused.
    :param parent: parent limb number, ``None`` for the torso.
    :param site: attachment site on the parent: ``"torso"``, ``"mid"`` or ``"btm"``.
    :param h: limb length between the caps.
    :param theta: azimuth of the limb direction, degrees.
    :param phi: polar angle of the limb direction, degrees.
    :param hinges: the limb's hinges, ``x`` before ``y``.
    :param mirrored: member of a mirrored pair (its own sites are ``mirror_growth_site``).
    :param theta_rad: θ in radians when it was derived as DERL derives it (``2π - θ`` of another
        angle); ``None``: ``radians(theta)``.
    """

    idx: int
    parent: int | None
    site: str
    h: float
    theta: int
    phi: int
    hinges: tuple[Hinge, ...]
    mirrored: bool
    theta_rad: float | None = None

    @property
    def name(self) -> str:
        return f"limb/{self.idx}"

    @property
    def radians(self) -> tuple[float, float]:
        """(θ, φ) in radians as DERL computes them: ``theta_rad`` when the limb is a mirror image or
        a flipped pair member (``2π - θ``, see :func:`sph2cart`), else ``radians(theta)``."""
        theta = math.radians(self.theta) if self.theta_rad is None else self.theta_rad
        return theta, math.radians(self.phi)

    @property
    def parent_name(self) -> str:
        return TORSO if self.parent is None else f"limb/{self.parent}"

    @property
    def site_name(self) -> str:
        return TORSO if self.parent is None else f"limb/{self.site}/{self.parent}"

    @property
    def axes(self) -> str:
        return "".join(h.axis for h in self.hinges)

    @property
    def direction(self) -> Vec3:
        """Unit direction on DERL's rounded grid (straight down is one direction for every θ)."""
        return sph2cart(1.0, *self.radians)


@dataclass(frozen=True)
class GrowthSite:
    """A site where limbs can grow: the torso centre, or the ``mid``/``btm`` site of a limb.

    :param limb: owning limb number, ``None`` for the torso.
    :param kind: ``"torso"``, ``"mid"`` or ``"btm"``.
    :param mirror: ``True`` for a ``mirror_growth_site`` (the limb belongs to a mirrored pair).
    """

    limb: int | None
    kind: str
    mirror: bool

    @property
    def name(self) -> str:
        return TORSO if self.limb is None else f"limb/{self.kind}/{self.limb}"


@dataclass
class UnimalGenome:
    """Everything that defines a UNIMAL robot; the XML is derived from it.

    :param torso_density: density of the torso sphere.
    :param limb_density: density shared by all limbs.
    :param torso_mode: which unused torso-growth site the torso carries (DERL layout).
    :param limbs: limbs by number, in creation order (= sibling order in the file).
    :param groups: limb groups: ``(k,)`` or a mirrored pair ``(k, k+1)`` (first member on +y).
    :param allowed_pairs: geom-name pairs allowed to touch in the self-collision test.
    :param next_idx: number of the next limb to be created.
    """

    torso_density: int
    limb_density: int
    torso_mode: str
    limbs: dict[int, Limb] = field(default_factory=dict)
    groups: list[tuple[int, ...]] = field(default_factory=list)
    allowed_pairs: set[tuple[str, str]] = field(default_factory=set)
    next_idx: int = 0

    def copy(self) -> UnimalGenome:
        """An independent copy (limbs and hinges are immutable, so containers are enough)."""
        return replace(self, limbs=dict(self.limbs), groups=list(self.groups), allowed_pairs=set(self.allowed_pairs))

    @property
    def num_limbs(self) -> int:
        return len(self.limbs)

    @property
    def dof(self) -> int:
        return sum(len(limb.hinges) for limb in self.limbs.values())

    def children(self, parent: int | None) -> list[Limb]:
        """Direct children of a limb (``None``: of the torso), in creation order."""
        return [limb for limb in self.limbs.values() if limb.parent == parent]

    def walk(self, parent: int | None = None) -> Iterator[Limb]:
        """Limbs in document order (depth-first pre-order, siblings in creation order)."""
        for child in self.children(parent):
            yield child
            yield from self.walk(child.idx)

    def growth_sites(self) -> list[GrowthSite]:
        """Every growth site of the tree, in document order."""
        sites = [GrowthSite(None, "torso", False)]
        for limb in self.walk():
            sites += [GrowthSite(limb.idx, "mid", limb.mirrored), GrowthSite(limb.idx, "btm", limb.mirrored)]
        return sites

    def partner(self, idx: int | None) -> int | None:
        """The mirror partner of a limb, if it belongs to a pair."""
        for group in self.groups:
            if idx in group and len(group) == 2:
                return group[1] if group[0] == idx else group[0]
        return None

    def mirror_site(self, site: GrowthSite) -> GrowthSite:
        """The mirror counterpart of a ``mirror_growth_site``."""
        partner = self.partner(site.limb)
        if partner is None:
            raise ValueError(f"{site.name} is not a mirror growth site")
        return GrowthSite(partner, site.kind, True)

    def depth(self) -> int:
        """Number of limb levels below the torso."""

        def level(limb: Limb) -> int:
            return 1 if limb.parent is None else 1 + level(self.limbs[limb.parent])

        return max((level(limb) for limb in self.limbs.values()), default=0)


# --------------------------------------------------------------------------------------- layout
@dataclass(frozen=True)
class LimbLayout:
    """Coordinates of one limb in its body frame (= world orientation), DERL's 2-decimal grid.

    :param pos: body origin in the parent body frame (on the parent's surface).
    :param joint_pos: hinge anchor: back on the parent axis / inside the torso.
    :param tip: capsule ``fromto`` end (start is the body origin).
    :param mid: ``limb/mid/k`` site.
    :param btm: ``limb/btm/k`` site (capsule end).
    :param btm_pos: ``limb/btm_pos/k`` site: the capsule's outermost point.
    """

    pos: Vec3
    joint_pos: Vec3
    tip: Vec3
    mid: Vec3
    btm: Vec3
    btm_pos: Vec3


def _site_position(genome: UnimalGenome, limb: Limb) -> Vec3:
    """Position of a limb's attachment site in its parent's frame."""
    if limb.parent is None:
        return (0.0, 0.0, 0.0)
    parent = genome.limbs[limb.parent]
    reach = LIMB_RADIUS + (parent.h / 2 if limb.site == "mid" else parent.h)
    return sph2cart(reach, *parent.radians)


def limb_layout(genome: UnimalGenome, limb: Limb) -> LimbLayout:
    """Derive a limb's coordinates from its parameters (spec §1.2).

    :param genome: the robot (for the parent's geometry).
    :param limb: the limb.
    """
    r, h = LIMB_RADIUS, limb.h
    t, p = limb.radians
    parent_radius = TORSO_RADIUS if limb.parent is None else LIMB_RADIUS
    # DERL places the hinge anchor along the opposite direction (π + θ, π - φ) rounded on its own.
    t_joint = math.pi + t
    if t_joint >= 2 * math.pi:
        t_joint -= 2 * math.pi
    return LimbLayout(
        pos=_add(_site_position(genome, limb), sph2cart(parent_radius, t, p)),
        joint_pos=sph2cart(r, t_joint, math.pi - p),
        tip=sph2cart(r + h, t, p),
        mid=sph2cart(r + h / 2, t, p),
        btm=sph2cart(r + h, t, p),
        btm_pos=sph2cart(2 * r + h, t, p),
    )


def _unused_torso_site(genome: UnimalGenome) -> Vec3:
    """DERL's site for extra torsos (never used: UNIMALs have one torso), kept for the file layout."""
    return (-TORSO_RADIUS, 0.0, 0.0) if genome.torso_mode == "horizontal_y" else (0.0, 0.0, -TORSO_RADIUS)


# ------------------------------------------------------------------------------------ MjSpec side
@lru_cache(maxsize=1)
def _template_text() -> str:
    return TEMPLATE_PATH.read_text()


@lru_cache(maxsize=1)
def _physics_template() -> str:
    """The template without looks (assets, visual, materials): compiles ~10x faster for the tests."""
    root = ET.fromstring(_template_text())
    for tag in ("asset", "visual"):
        for elem in root.findall(tag):
            root.remove(elem)
    for elem in root.iter():
        elem.attrib.pop("material", None)
    _find(root, "default/geom").set("margin", repr(CONTACT_MARGIN))
    return ET.tostring(root, encoding="unicode")


@lru_cache(maxsize=1)
def _physics_base() -> mujoco.MjSpec:
    """Parsed once; every probe starts from a copy (10x cheaper than parsing)."""
    return mujoco.MjSpec.from_string(_physics_template())


def build_spec(genome: UnimalGenome, axes: dict[str, Vec3] | None = None, torso_z: float = 0.0) -> mujoco.MjSpec:
    """The robot's body tree as an :class:`mujoco.MjSpec` on the physics part of the template.

    Holds bodies, joints, geoms and sites exactly as :func:`write_xml` writes them, plus the
    acceptance test's contact margin on every geom; no motors, sensors, camera or looks (use
    :meth:`GeneratedUnimal.spec` for the complete robot).

    :param genome: the robot.
    :param axes: hinge axes by joint name; default (1,0,0)/(0,1,0) (irrelevant at ``qpos0``).
    :param torso_z: torso height.
    """
    spec = _physics_base().copy()
    classes = ("free", "normal_joint", "imu_vel", "touch_site", "btm_pos_site", "torso_growth_site")
    defaults = {name: spec.find_default(name) for name in classes}
    growth = {False: spec.find_default("growth_site"), True: spec.find_default("mirror_growth_site")}
    torso = spec.worldbody.add_body(name=TORSO, pos=[0.0, 0.0, torso_z])
    torso.add_joint(defaults["free"], name="root", type=mujoco.mjtJoint.mjJNT_FREE)
    torso.add_site(defaults["imu_vel"], name="root")
    torso.add_geom(name=TORSO, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[TORSO_RADIUS, 0, 0], density=genome.torso_density)
    torso.add_site(growth[False], name=TORSO, pos=[0, 0, 0])
    torso.add_site(defaults["btm_pos_site"], name="torso/btm_pos/0", pos=[0, 0, -TORSO_RADIUS])
    torso.add_site(defaults["touch_site"], name="torso/touch/0", size=[TORSO_RADIUS + 0.01, 0, 0])
    torso.add_site(defaults["torso_growth_site"], name=f"torso/{genome.torso_mode}/0", pos=list(_unused_torso_site(genome)))
    bodies: dict[int | None, Any] = {None: torso}  # by limb index, the torso's None
    for limb in genome.walk():
        lay = limb_layout(genome, limb)
        body = bodies[limb.parent].add_body(name=limb.name, pos=list(lay.pos))
        for hinge in limb.hinges:
            name = f"limb{hinge.axis}/{limb.idx}"
            default_axis = (1.0, 0.0, 0.0) if hinge.axis == "x" else (0.0, 1.0, 0.0)
            body.add_joint(
                defaults["normal_joint"],
                name=name,
                type=mujoco.mjtJoint.mjJNT_HINGE,
                pos=list(lay.joint_pos),
                axis=list((axes or {}).get(name, default_axis)),
                range=list(hinge.range),
            )
        fromto = [0.0, 0.0, 0.0, *lay.tip]
        body.add_geom(
            name=limb.name,
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=fromto,
            size=[LIMB_RADIUS, 0, 0],
            density=genome.limb_density,
        )
        body.add_site(growth[limb.mirrored], name=f"limb/mid/{limb.idx}", pos=list(lay.mid))
        body.add_site(growth[limb.mirrored], name=f"limb/btm/{limb.idx}", pos=list(lay.btm))
        body.add_site(defaults["btm_pos_site"], name=f"limb/btm_pos/{limb.idx}", pos=list(lay.btm_pos))
        body.add_site(
            defaults["touch_site"],
            name=f"limb/touch/{limb.idx}",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            size=[LIMB_RADIUS + 0.01, 0, 0],
            fromto=fromto,
        )
        bodies[limb.idx] = body
    return spec


@dataclass
class _Probe:
    """A compiled robot at ``qpos0`` after ``mj_forward`` (the acceptance-test setting)."""

    model: mujoco.MjModel
    data: mujoco.MjData

    @classmethod
    def of(cls, genome: UnimalGenome, filterparent: bool = False) -> _Probe:
        model = build_spec(genome).compile()
        if filterparent:
            model.opt.disableflags &= ~_FILTERPARENT
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        return cls(model, data)

    def com_y(self) -> float:
        return float(self.data.subtree_com[self.model.body(TORSO).id, 1])

    def contacts(self) -> set[tuple[str, str]]:
        """Touching geom pairs, as sorted name pairs."""
        pairs = set()
        for c in self.data.contact[: self.data.ncon]:
            a, b = self.model.geom(c.geom1).name, self.model.geom(c.geom2).name
            pairs.add((min(a, b), max(a, b)))
        return pairs


def _pair(a: str, b: str) -> tuple[str, str]:
    return (min(a, b), max(a, b))


def is_valid(genome: UnimalGenome, extra_allowed: AbstractSet[tuple[str, str]] = frozenset()) -> bool:
    """The acceptance test: symmetric, and no self-contact outside the allowed pairs.

    :param genome: the candidate robot.
    :param extra_allowed: pairs allowed on top of ``genome.allowed_pairs`` (those of new limbs).
    """
    probe = _Probe.of(genome)
    if abs(probe.com_y()) >= SYMMETRY_TOLERANCE:
        return False
    return probe.contacts() <= (genome.allowed_pairs | extra_allowed)


# -------------------------------------------------------------------------------------- sampling
def _pick(rng: np.random.Generator, options: Sequence):
    """Uniform choice through ``integers`` only (its stream is stable across NumPy versions)."""
    return options[int(rng.integers(len(options)))]


def _sample_hinges(rng: np.random.Generator, axes: str) -> tuple[Hinge, ...]:
    return tuple(Hinge(axis, _pick(rng, JOINT_RANGES), _pick(rng, GEARS)) for axis in axes)


def new_genome(rng: np.random.Generator) -> UnimalGenome:
    """A torso without limbs, with sampled densities and torso layout.

    :param rng: the random generator.
    """
    torso_mode = _pick(rng, TORSO_MODES)
    return UnimalGenome(torso_density=_pick(rng, DENSITIES), limb_density=_pick(rng, DENSITIES), torso_mode=torso_mode)


# ------------------------------------------------------------------------------------- mutations
def _try_grow(genome: UnimalGenome, rng: np.random.Generator) -> UnimalGenome | None:
    """One ``grow_limb`` attempt (spec §1.6 steps 1-5); ``None`` if rejected."""
    site = _pick(rng, genome.growth_sites())
    if site.mirror:
        # Start from the pair's +y member so both orders give the same robot.
        other = genome.mirror_site(site)
        site = min(site, other, key=lambda s: s.limb)
        count = 2
    else:
        count = 1 + int(rng.integers(2))
    if genome.num_limbs + count > MAX_LIMBS:
        return None
    h = _pick(rng, LIMB_HEIGHTS)
    hinges = _sample_hinges(rng, _pick(rng, JOINT_AXES))
    theta, phi = _pick(rng, THETAS), _pick(rng, PHIS)
    theta_rad = None
    if count == 2 and theta > 180:
        theta, theta_rad = 360 - theta, 2 * math.pi - math.radians(theta)  # DERL flips in radians
    first = Limb(genome.next_idx, site.limb, site.kind, h, theta, phi, hinges, mirrored=count == 2, theta_rad=theta_rad)
    if site.limb is not None:
        parent_dir = genome.limbs[site.limb].direction
        if site.kind == "mid" and first.direction == parent_dir:
            return None
        if first.direction == _neg(parent_dir):
            return None  # folded back inside the parent (our addition, see module docstring)
    new = [first]
    if count == 2:
        if not site.mirror:
            if theta in (0, 180) or phi == 180:
                return None  # the mirror image would coincide with the limb
            new.append(replace(first, idx=first.idx + 1, theta=360 - theta, theta_rad=2 * math.pi - first.radians[0]))
        else:
            twin = genome.mirror_site(site)
            new.append(replace(first, idx=first.idx + 1, parent=twin.limb, site=twin.kind))
    allowed = {_pair(limb.parent_name, limb.name) for limb in new}
    if count == 2 and not site.mirror:
        allowed.add(_pair(new[0].name, new[1].name))
    candidate = genome.copy()
    for limb in new:
        candidate.limbs[limb.idx] = limb
    if not is_valid(candidate, allowed):
        return None
    candidate.allowed_pairs |= allowed
    candidate.groups.append(tuple(limb.idx for limb in new))
    candidate.next_idx += count
    return candidate


def grow_limb(genome: UnimalGenome, rng: np.random.Generator) -> UnimalGenome:
    """Add one limb or a mirrored pair (up to 50 attempts); unchanged if every attempt fails.

    :param genome: the robot (not modified).
    :param rng: the random generator.
    """
    for _ in range(GROW_ATTEMPTS):
        grown = _try_grow(genome, rng)
        if grown is not None:
            return grown
    return genome


def _joint_scope(genome: UnimalGenome, rng: np.random.Generator) -> list[tuple[int, ...]]:
    """DERL's scope rule: all limb groups, or one random group (50/50)."""
    if int(rng.integers(2)) == 0:
        return list(genome.groups)
    return [_pick(rng, genome.groups)]


def _mutate_joints(genome: UnimalGenome, rng: np.random.Generator, op: str) -> UnimalGenome:
    """``joint_angle`` (ranges), ``gear`` (gears) or ``dof`` (axes, ranges and gears)."""
    out = genome.copy()
    for group in _joint_scope(genome, rng):
        old = genome.limbs[group[0]].hinges
        if op == "dof":
            hinges = _sample_hinges(rng, _pick(rng, JOINT_AXES))
        elif op == "joint_angle":
            hinges = tuple(replace(hg, range=_pick(rng, JOINT_RANGES)) for hg in old)
        else:
            hinges = tuple(replace(hg, gear=_pick(rng, GEARS)) for hg in old)
        for idx in group:  # a pair shares its joint parameters
            out.limbs[idx] = replace(out.limbs[idx], hinges=hinges)
    return out


def _mutate_limb_params(genome: UnimalGenome, rng: np.random.Generator) -> UnimalGenome:
    """Change the length of one limb group; children follow their attachment sites."""
    for _ in range(GROW_ATTEMPTS):
        group = _pick(rng, genome.groups)
        current = genome.limbs[group[0]].h
        h = _pick(rng, [x for x in LIMB_HEIGHTS if x != current])
        candidate = genome.copy()
        for idx in group:
            candidate.limbs[idx] = replace(candidate.limbs[idx], h=h)
        if is_valid(candidate):
            return candidate
    return genome


def _mutate_density(genome: UnimalGenome, rng: np.random.Generator) -> UnimalGenome:
    out = genome.copy()
    out.limb_density = _pick(rng, DENSITIES)
    out.torso_density = _pick(rng, DENSITIES)
    return out


def _delete_limb(genome: UnimalGenome, rng: np.random.Generator) -> UnimalGenome:
    """Remove one random leaf group (a group none of whose limbs has children)."""
    parents = {limb.parent for limb in genome.limbs.values()}
    leaves = [group for group in genome.groups if not parents.intersection(group)]
    group = _pick(rng, leaves)
    names = {f"limb/{idx}" for idx in group}
    out = genome.copy()
    for idx in group:
        del out.limbs[idx]
    out.groups.remove(group)
    out.allowed_pairs = {pair for pair in out.allowed_pairs if not names.intersection(pair)}
    return out


def allowed_mutations(genome: UnimalGenome) -> tuple[str, ...]:
    """Mutation operators applicable to a robot (DERL's restrictions).

    :param genome: the robot.
    """
    if genome.num_limbs == 0:
        return ("grow_limb",)
    ops = list(MUTATION_OPS)
    if genome.num_limbs >= MAX_LIMBS:
        ops.remove("grow_limb")
    if genome.num_limbs <= 2:
        ops.remove("delete_limb")
    return tuple(ops)


def mutate_genome(genome: UnimalGenome, rng: np.random.Generator, op: str | None = None) -> tuple[UnimalGenome, str]:
    """Apply one mutation operator; returns the new genome and the operator used.

    The input is never modified. An operator that finds no valid change (``grow_limb`` or
    ``limb_params`` after 50 rejected attempts) returns the input genome itself.

    :param genome: the robot.
    :param rng: the random generator.
    :param op: operator name from :data:`MUTATION_OPS`; ``None`` draws one uniformly among
        :func:`allowed_mutations`.
    :raises ValueError: unknown operator, or one not applicable to this robot.
    """
    ops = allowed_mutations(genome)
    if op is None:
        op = _pick(rng, ops)
    elif op not in MUTATION_OPS:
        raise ValueError(f"unknown mutation '{op}'; choose from {list(MUTATION_OPS)}")
    elif op not in ops:
        raise ValueError(f"mutation '{op}' does not apply to a robot with {genome.num_limbs} limbs")
    if op == "grow_limb":
        return grow_limb(genome, rng), op
    if op in ("joint_angle", "gear", "dof"):
        return _mutate_joints(genome, rng, op), op
    if op == "limb_params":
        return _mutate_limb_params(genome, rng), op
    if op == "density":
        return _mutate_density(genome, rng), op
    return _delete_limb(genome, rng), op


def generate_genome(seed: int, num_limbs: int | None = None) -> UnimalGenome:
    """Grow a new robot: torso, ``grow_limb``, then random mutations up to the limb target.

    :param seed: seed of ``np.random.default_rng``; the only source of randomness.
    :param num_limbs: limb target (1-10); the robot ends with at least this many limbs (one
        more if the last growth added a pair). Default: uniform over :data:`TARGET_LIMBS`.
    :raises ValueError: target outside 1-10.
    """
    rng = np.random.default_rng(seed)
    target = _pick(rng, TARGET_LIMBS) if num_limbs is None else int(num_limbs)
    if not 1 <= target <= MAX_LIMBS:
        raise ValueError(f"num_limbs must lie in 1..{MAX_LIMBS}, got {num_limbs}")
    for _ in range(MAX_RESTARTS):
        genome = grow_limb(new_genome(rng), rng)
        for _ in range(MAX_MUTATIONS):
            if genome.num_limbs >= target:
                return genome
            genome, _op = mutate_genome(genome, rng)
    raise RuntimeError(f"seed {seed}: no robot with {target} limbs after {MAX_RESTARTS} restarts")


# ------------------------------------------------------------------------------------- finalize
def _fmt(x: float, decimals: int) -> str:
    """Fixed formatting: at most ``decimals`` decimals, no trailing zeros, never ``-0``."""
    text = f"{_clean(float(x), decimals):.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _vec(values: Sequence[float], decimals: int = 2) -> str:
    return " ".join(_fmt(v, decimals) for v in values)


def _find(root: ET.Element, path: str) -> ET.Element:
    """``root.find(path)``, an element the bundled template has."""
    found = root.find(path)
    if found is None:
        raise ValueError(f"the morphology template has no <{path}>")
    return found


def _elem(parent: ET.Element, tag: str, **attrs: str) -> ET.Element:
    return ET.SubElement(parent, tag, {key.rstrip("_"): value for key, value in attrs.items()})


@dataclass(frozen=True)
class _Finish:
    """What saving reads from the compiled robot."""

    axes: dict[str, Vec3]
    torso_z: float
    excludes: list[tuple[str, str]]


def _measure(genome: UnimalGenome) -> _Finish:
    """Hinge axes from the capsule frames, spawn height, and contacts left with filterparent on."""
    probe = _Probe.of(genome, filterparent=True)
    model, data = probe.model, probe.data
    axes: dict[str, Vec3] = {}
    for limb in genome.limbs.values():
        frame = data.geom_xmat[model.geom(limb.name).id].reshape(3, 3)
        for hinge in limb.hinges:
            column = frame[:, 0 if hinge.axis == "x" else 1]
            x, y, z = (_clean(float(v), 4) for v in column)
            axes[f"limb{hinge.axis}/{limb.idx}"] = (x, y, z)
    lowest = min(float(data.site_xpos[s, 2]) for s in range(model.nsite) if "/btm_pos/" in model.site(s).name)
    bodies = sorted((model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]) for c in data.contact[: data.ncon])
    excludes = []
    for a, b in dict.fromkeys(tuple(sorted(pair)) for pair in bodies):
        excludes.append((model.body(a).name, model.body(b).name))
    return _Finish(axes=axes, torso_z=_clean(-lowest + FLOOR_OFFSET, 2), excludes=excludes)


def write_xml(genome: UnimalGenome, finish: _Finish, comment: str) -> str:
    """The robot file: the template with the robot, motors, sensors and excludes filled in.

    :param genome: the robot.
    :param finish: measured axes, spawn height and excludes.
    :param comment: provenance line written at the top of ``<mujoco>``.
    """
    root = ET.fromstring(_template_text(), parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    root.insert(0, ET.Comment(f" {comment} "))
    torso = _elem(_find(root, "worldbody"), "body", name=TORSO, pos=_vec((0, 0, finish.torso_z)))
    _elem(torso, "joint", name="root", type="free", class_="free")
    _elem(torso, "site", name="root", class_="imu_vel")
    _elem(
        torso, "geom", name=TORSO, type="sphere", size=_fmt(TORSO_RADIUS, 2), condim="3",
        density=str(genome.torso_density),
    )  # fmt: skip
    # Side view that follows the robot from 4 m, looking slightly down.
    _elem(torso, "camera", name="side", pos="0 -4 1.2", xyaxes="1 0 0 0 0.3 1", mode="trackcom")
    _elem(torso, "site", name=TORSO, class_="growth_site", pos="0 0 0")
    _elem(torso, "site", name="torso/btm_pos/0", class_="btm_pos_site", pos=_vec((0, 0, -TORSO_RADIUS)))
    _elem(torso, "site", name="torso/touch/0", class_="touch_site", size=_fmt(TORSO_RADIUS + 0.01, 2))
    unused = _unused_torso_site(genome)
    _elem(torso, "site", name=f"torso/{genome.torso_mode}/0", class_="torso_growth_site", pos=_vec(unused))
    bodies: dict[int | None, ET.Element] = {None: torso}  # by limb index, the torso's None
    for limb in genome.walk():
        lay = limb_layout(genome, limb)
        body = _elem(bodies[limb.parent], "body", name=limb.name, pos=_vec(lay.pos))
        for hinge in limb.hinges:
            name = f"limb{hinge.axis}/{limb.idx}"
            _elem(
                body, "joint", name=name, type="hinge", class_="normal_joint", range=_vec(hinge.range, 0),
                pos=_vec(lay.joint_pos), axis=_vec(finish.axes[name], 4),
            )  # fmt: skip
        fromto = _vec((0, 0, 0, *lay.tip))
        site_class = "mirror_growth_site" if limb.mirrored else "growth_site"
        _elem(
            body, "geom", name=limb.name, type="capsule", fromto=fromto, size=_fmt(LIMB_RADIUS, 2),
            density=str(genome.limb_density),
        )  # fmt: skip
        _elem(body, "site", name=f"limb/mid/{limb.idx}", class_=site_class, pos=_vec(lay.mid))
        _elem(body, "site", name=f"limb/btm/{limb.idx}", class_=site_class, pos=_vec(lay.btm))
        _elem(body, "site", name=f"limb/btm_pos/{limb.idx}", class_="btm_pos_site", pos=_vec(lay.btm_pos))
        _elem(
            body, "site", name=f"limb/touch/{limb.idx}", class_="touch_site", type="capsule",
            size=_fmt(LIMB_RADIUS + 0.01, 2), fromto=fromto,
        )  # fmt: skip
        bodies[limb.idx] = body
    # Motors follow the joints' document order, so actuator k drives hinge k (MetaMorph relies on it).
    actuator = _find(root, "actuator")
    for limb in genome.walk():
        for hinge in limb.hinges:
            name = f"limb{hinge.axis}/{limb.idx}"
            _elem(actuator, "motor", name=name, joint=name, gear=str(hinge.gear))
    sensor = _find(root, "sensor")
    _elem(sensor, "accelerometer", name="torso_accel", site="root")
    _elem(sensor, "gyro", name="torso_gyro", site="root")
    _elem(sensor, "velocimeter", name="torso_vel", site="root")
    _elem(sensor, "subtreeangmom", name="unimal_am", body=TORSO)
    _elem(sensor, "touch", name=TORSO, site="torso/touch/0")
    for limb in genome.walk():
        _elem(sensor, "touch", name=limb.name, site=f"limb/touch/{limb.idx}")
    contact = _find(root, "contact")
    for a, b in finish.excludes:
        _elem(contact, "exclude", name=f"{a}:{b}", body1=a, body2=b)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def unimal_metadata(genome: UnimalGenome) -> dict:
    """The unimals_100 metadata: ``{"dof", "num_limbs", "symmetric_limbs": [[k, k+1], ...]}``.

    :param genome: the robot.
    """
    pairs = [list(group) for group in genome.groups if len(group) == 2]
    return {"dof": genome.dof, "num_limbs": genome.num_limbs, "symmetric_limbs": pairs}


@dataclass(frozen=True)
class GeneratedUnimal:
    """A generated robot: its file text, metadata and the genome it came from.

    :param name: robot name (file stem), e.g. ``train-000``.
    :param xml: the MJCF text (unimals_100 layout, our template).
    :param metadata: the unimals_100 metadata dict.
    :param genome: the parameters, for further mutation.
    :param provenance: how it was made (also written as a comment in the file).
    :param torso_height: spawn height of the torso written in the file (lowest point 0.2 above z=0).
    """

    name: str
    xml: str
    metadata: dict
    genome: UnimalGenome = field(repr=False)
    provenance: str = ""
    torso_height: float = 0.0

    @property
    def metadata_json(self) -> str:
        """The metadata file text (2-space indented JSON, newline-terminated)."""
        return json.dumps(self.metadata, indent=2) + "\n"

    def spec(self) -> mujoco.MjSpec:
        """A fresh, editable :class:`mujoco.MjSpec` of the complete robot file."""
        return mujoco.MjSpec.from_string(self.xml)

    def morphology(self) -> Morphology:
        """The robot as the loader sees it (validates it on the way)."""
        return parse_morphology(self.xml, self.name)

    def write(self, out_dir: str | Path) -> tuple[Path, Path]:
        """Write ``out_dir/xml/<name>.xml`` and ``out_dir/metadata/<name>.json``.

        :param out_dir: set directory (unimals_100 layout); created if needed.
        """
        out_dir = Path(out_dir)
        xml_path = out_dir / "xml" / f"{self.name}.xml"
        meta_path = out_dir / "metadata" / f"{self.name}.json"
        xml_path.parent.mkdir(parents=True, exist_ok=True)
        meta_path.parent.mkdir(parents=True, exist_ok=True)
        xml_path.write_text(self.xml)
        meta_path.write_text(self.metadata_json)
        return xml_path, meta_path


def finalize(genome: UnimalGenome, name: str, provenance: str) -> GeneratedUnimal:
    """Turn a genome into a saved-form robot (axes, spawn height, sensors, excludes).

    :param genome: the robot; needs at least one limb.
    :param name: robot name.
    :param provenance: one line recording how it was made.
    """
    if genome.num_limbs == 0:
        raise ValueError("a UNIMAL robot needs at least one limb")
    finish = _measure(genome)
    xml = write_xml(genome, finish, f"{name}: {provenance}")
    return GeneratedUnimal(
        name=name,
        xml=xml,
        metadata=unimal_metadata(genome),
        genome=genome,
        provenance=provenance,
        torso_height=finish.torso_z,
    )


PROVENANCE_PREFIX = "divmorph UNIMAL generator"


def generate_unimal(seed: int, num_limbs: int | None = None, name: str | None = None) -> GeneratedUnimal:
    """Generate one UNIMAL robot, deterministically from ``seed``.

    :param seed: seed of ``np.random.default_rng``; equal seeds give byte-identical files.
    :param num_limbs: limb target (see :func:`generate_genome`); default uniform over 5-10.
    :param name: robot name; default ``unimal-<seed>``.
    """
    return finalize(generate_genome(seed, num_limbs), name or f"unimal-{seed}", seed_provenance(seed, num_limbs))


def seed_provenance(seed: int, num_limbs: int | None = None) -> str:
    """The provenance line of :func:`generate_unimal` (also parsed back by the sets module).

    :param seed: generator seed.
    :param num_limbs: limb target, if one was given.
    """
    target = "" if num_limbs is None else f", num_limbs={num_limbs}"
    return f"{PROVENANCE_PREFIX}, seed={seed}{target}"


def mutate(unimal: GeneratedUnimal, seed: int, op: str | None = None, name: str | None = None) -> GeneratedUnimal:
    """A mutated child of a generated robot (one operator of :data:`MUTATION_OPS`).

    :param unimal: the parent robot (unchanged).
    :param seed: seed of the child's ``np.random.default_rng``.
    :param op: operator name; ``None`` draws one among those that apply.
    :param name: child name; default ``<parent>-<op>-<seed>``.
    :raises ValueError: unknown operator, or one not applicable (e.g. ``grow_limb`` at 10 limbs).
    """
    genome, used = mutate_genome(unimal.genome, np.random.default_rng(seed), op)
    child = name or f"{unimal.name}-{used}-{seed}"
    return finalize(genome, child, f"{PROVENANCE_PREFIX}, mutation {used} of {unimal.name}, seed={seed}")
