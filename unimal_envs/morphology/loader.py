"""Load UNIMAL robots from MJCF files and turn them into padded per-token descriptions.

A UNIMAL robot is a tree of rigid bodies: a spherical torso ``torso/0`` with a free joint, and
capsule limbs ``limb/<k>``, each actuated by one or two hinges (an "x" and/or a "y" hinge, one
motor each). The loader accepts the official unimals_100 files unchanged, as well as the files
written by :mod:`unimal_envs.morphology.generator`.

Each robot becomes a :class:`Morphology`: token order (torso first, then limbs in MuJoCo body
order), the hinges of every token, masks, and every *static* per-token feature of the
observation contract (:mod:`unimal_envs.contract`). Static features are read from the robot file
alone, so they are identical for every task and arena the robot is placed in.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from unimal_envs import contract as C
from unimal_envs.morphology.cache import OFFICIAL_SETS, SUBSETS, official_set_dir
from unimal_envs.morphology.errors import MorphologyError  # noqa: F401 -- raised here, importable from here

TORSO = "torso/0"
#: Torso height above the lowest body point at spawn, added by the generator (DERL FLOOR_OFFSET).
FLOOR_OFFSET = 0.2
SHIPPED_SETS = ("train", "novel")
#: Height of the floor's top in MetaMorph's worlds (a 1 m half-thick box at the origin); ours is at 0.
REFERENCE_FLOOR_TOP = 1.0
_DATA_DIR = Path(__file__).resolve().parent.parent / "data" / "morphologies"

# ModuMorph's fixed rescaling bounds for the context features: x' = 2 (x - lo) / (hi - lo) - 1.
_Q = 0.7071
_LIMB_CONTEXT_BOUNDS = np.array(
    [
        # body_pos (3)            body_ipos (3)              body_iquat (4)         geom_quat (4)        mass   shape (2)
        [-0.5, -0.45, -0.49, -0.225, -0.225, -0.225, _Q, -_Q, -_Q, 0, _Q, -_Q, -_Q, 0, 1.178, 0.05, 0.0],
        [0.5, 0.45, 2.04, 0.225, 0.225, 0.0, 1, _Q, _Q, 0, 1, _Q, _Q, 0, 4.189, 0.1, 0.2263],
    ]
)
_HINGE_CONTEXT_BOUNDS = np.array(
    [
        # jnt_pos (3)        range (2)          axis (3)          gear
        [-0.05, -0.05, 0.0, -math.pi / 2, 0.0, -0.5, -0.5, -1.0, 0.0],
        [0.05, 0.05, 0.05, 0.0, math.pi / 2, 1.0, 1.0, 1.0, 300.0],
    ]
)


def _rescale(values: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    lo, hi = bounds
    span = hi - lo
    out = np.where(span > 0, 2.0 * (values - lo) / np.where(span > 0, span, 1.0) - 1.0, 0.0)
    return np.clip(out, -1.0, 1.0)


@dataclass(frozen=True, eq=False)
class Morphology:
    """One UNIMAL robot, ready to be placed in an arena.

    :param name: file stem, e.g. ``floor-1409-0-12-01-12-30-07``.
    :param xml: the robot's MJCF text, as read.
    :param tokens: body names, torso first, in MuJoCo body order (the policy's token order).
    :param hinges: per token, the ``(x_hinge, y_hinge)`` joint names (``None`` where absent).
    :param symmetric_limbs: pairs of token indices that are mirror images across the xz-plane.
    :param proprio_static: (12, 52) proprioceptive template: static columns filled, dynamic ones 0.
    :param context: (12, 35) morphology context rescaled to [-1, 1].
    :param obs_padding_mask: (12,) 1.0 for padded tokens.
    :param act_padding_mask: (24,) 1.0 for action slots without a hinge.
    :param torso_height: spawn height of the torso above flat ground (the file's height, lifted
        if the robot would start inside the floor).
    :param standing_height: ``torso_height - FLOOR_OFFSET`` (MetaMorph's ``orig_height``): the
        torso's height when the robot stands on its lowest point; fall thresholds are fractions of it.
    :param path: the file it came from, if any.
    """

    name: str
    xml: str
    tokens: tuple[str, ...]
    hinges: tuple[tuple[str | None, str | None], ...]
    symmetric_limbs: tuple[tuple[int, int], ...]
    proprio_static: np.ndarray = field(repr=False)
    context: np.ndarray = field(repr=False)
    obs_padding_mask: np.ndarray = field(repr=False)
    act_padding_mask: np.ndarray = field(repr=False)
    torso_height: float = 0.0
    standing_height: float = 0.0
    path: Path | None = None

    def __post_init__(self) -> None:
        # read-only: one loaded morphology is shared by every env of a process (load_morphology)
        for array in (self.proprio_static, self.context, self.obs_padding_mask, self.act_padding_mask):
            array.setflags(write=False)

    @property
    def num_tokens(self) -> int:
        return len(self.tokens)

    @property
    def num_limbs(self) -> int:
        return len(self.tokens) - 1

    @property
    def dof(self) -> int:
        return sum(h is not None for pair in self.hinges for h in pair)

    @property
    def depth(self) -> int:
        """Number of limb levels below the torso (1 = every limb attaches to the torso)."""
        depth = {TORSO: 0}
        for parent, child in self._edges():
            depth[child] = depth[parent] + 1
        return max(depth.values())

    def _edges(self) -> list[tuple[str, str]]:
        root = ET.fromstring(self.xml)
        return [(parent.get("name"), child.get("name")) for parent in root.iter("body") for child in parent.findall("body")]

    def spec(self) -> mujoco.MjSpec:
        """A fresh, editable :class:`mujoco.MjSpec` of the robot file."""
        return mujoco.MjSpec.from_string(self.xml)

    def __repr__(self) -> str:
        # One line: the dataclass repr would print the whole MJCF text and every token name.
        where = f", path={str(self.path)!r}" if self.path is not None else ""
        return f"Morphology(name={self.name!r}, limbs={self.num_limbs}, dof={self.dof}{where})"


def _fail(source: str, problem: str) -> MorphologyError:
    return MorphologyError(f"{source}: {problem}")


def _hinge_slot(joint_name: str, position: int) -> int:
    if joint_name.startswith("limbx"):
        return 0
    if joint_name.startswith("limby"):
        return 1
    return position


def parse_morphology(xml: str, name: str, source: str | None = None, path: Path | None = None) -> Morphology:
    """Validate an MJCF string as a UNIMAL robot and describe it.

    :param xml: MJCF text of the robot (the official unimals_100 layout, or the generator's).
    :param name: morphology name reported in ``info`` and tables.
    :param source: how to name the input in error messages (defaults to ``name``).
    :param path: the file the text came from, if any.
    :raises MorphologyError: malformed XML, MuJoCo compile errors, or a model that is not a UNIMAL
        (no ``torso/0``, non-hinge limb joints, unactuated hinges, more than 12 tokens, ...).
    """
    source = source or name
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as err:
        raise _fail(source, f"malformed XML ({err})") from None
    if root.tag != "mujoco":
        raise _fail(source, f"root element is <{root.tag}>, expected <mujoco> (an MJCF file)")
    try:
        spec = mujoco.MjSpec.from_string(xml)
        model = spec.compile()
    except Exception as err:  # MuJoCo raises ValueError with its own parser/compiler message
        raise _fail(source, f"MuJoCo could not compile it: {err}") from None

    torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, TORSO)
    if torso < 0:
        raise _fail(source, f"no body named '{TORSO}'; a UNIMAL robot has a torso body '{TORSO}'")
    if model.body_parentid[torso] != 0:
        raise _fail(source, f"'{TORSO}' must be a direct child of <worldbody>")
    # Tokens: the torso subtree in body order (depth-first pre-order = MuJoCo body order).
    bodies = [b for b in range(1, model.nbody) if model.body_rootid[b] == torso]
    if len(bodies) != model.nbody - 1:
        extra = [model.body(b).name for b in range(1, model.nbody) if model.body_rootid[b] != torso]
        raise _fail(source, f"bodies outside the '{TORSO}' tree are not part of a UNIMAL robot: {extra}")
    if len(bodies) > C.MAX_TOKENS:
        raise _fail(
            source,
            f"{len(bodies)} bodies (torso + {len(bodies) - 1} limbs) but at most {C.MAX_TOKENS} tokens fit "
            f"(torso + {C.MAX_TOKENS - 1} limbs)",
        )
    token_of_body = {b: i for i, b in enumerate(bodies)}

    # Joints: exactly one free joint on the torso, 1-2 hinges on every limb.
    hinge_ids: list[list[int]] = [[] for _ in bodies]
    for j in range(model.njnt):
        jtype = model.jnt_type[j]
        body = model.jnt_bodyid[j]
        jname = model.joint(j).name or f"joint #{j}"
        if body == torso:
            if jtype != mujoco.mjtJoint.mjJNT_FREE:
                raise _fail(source, f"torso joint '{jname}' must be a free joint")
            continue
        if jtype != mujoco.mjtJoint.mjJNT_HINGE:
            kind = mujoco.mjtJoint(jtype).name.removeprefix("mjJNT_").lower()
            raise _fail(source, f"joint '{jname}' is a {kind} joint; UNIMAL limbs have hinge joints only")
        hinge_ids[token_of_body[body]].append(j)
    if model.njnt == 0 or model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE or model.jnt_bodyid[0] != torso:
        raise _fail(source, f"'{TORSO}' needs a free joint (the robot's root) as the model's first joint")
    for b, ids in zip(bodies[1:], hinge_ids[1:]):
        if not 1 <= len(ids) <= C.SLOTS_PER_TOKEN:
            raise _fail(source, f"limb '{model.body(b).name}' has {len(ids)} hinges; a UNIMAL limb has 1 or 2")
        if model.body_geomnum[b] < 1:
            raise _fail(source, f"limb '{model.body(b).name}' has no geom")

    # Actuators: one motor per hinge (matched through the transmission, so order does not matter).
    gear_of_joint: dict[int, float] = {}
    for a in range(model.nu):
        j = int(model.actuator_trnid[a, 0])
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT or j < 0 or model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            raise _fail(source, f"actuator '{model.actuator(a).name}' does not drive a limb hinge")
        if j in gear_of_joint:
            raise _fail(source, f"hinge '{model.joint(j).name}' has more than one actuator")
        gear_of_joint[j] = float(model.actuator_gear[a, 0])
    unactuated = [model.joint(j).name for ids in hinge_ids for j in ids if j not in gear_of_joint]
    if unactuated:
        raise _fail(source, f"hinges without a motor: {unactuated}")

    # Static features, read at qpos0 of the robot alone.
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    proprio = np.zeros((C.MAX_TOKENS, C.PROPRIO_DIM))
    context = np.zeros((C.MAX_TOKENS, C.CONTEXT_DIM))
    act_mask = np.ones(C.ACTION_DIM, dtype=np.float32)
    hinges: list[tuple[str | None, str | None]] = []
    for t, b in enumerate(bodies):
        geom = model.body_geomadr[b]
        limb = np.concatenate(
            [
                model.body_pos[b],
                model.body_ipos[b],
                model.body_iquat[b],
                model.geom_quat[geom],
                [model.body_mass[b]],
                model.geom_size[geom, :2],
            ]
        )
        proprio[t, C.STATIC_BODY] = limb
        if t == 0:
            # ModuMorph's context reads the torso's body_pos in MetaMorph's world, whose floor top is
            # at z = 1 (its bounds reach z = 2.04 for that reason): add that offset for the context.
            limb = limb.copy()
            limb[2] += REFERENCE_FLOOR_TOP
        context[t, :17] = _rescale(limb, _LIMB_CONTEXT_BOUNDS)
        names: list[str | None] = [None, None]
        for position, j in enumerate(hinge_ids[t]):
            jname = model.joint(j).name
            slot = _hinge_slot(jname, position)
            if names[slot] is not None:
                raise _fail(source, f"limb '{model.body(b).name}' has two hinges in the same slot ({names[slot]}, {jname})")
            names[slot] = jname
            hinge = np.concatenate([model.jnt_pos[j], model.jnt_range[j], model.jnt_axis[j], [gear_of_joint[j]]])
            proprio[t, C.HINGE_SLOT_COLUMNS[slot]][C.HINGE_STATIC] = hinge
            context[t, 17 + 9 * slot : 26 + 9 * slot] = _rescale(hinge, _HINGE_CONTEXT_BOUNDS)
            act_mask[C.SLOTS_PER_TOKEN * t + slot] = 0.0
        hinges.append((names[0], names[1]))
    obs_mask = np.ones(C.MAX_TOKENS, dtype=np.float32)
    obs_mask[: len(bodies)] = 0.0

    # Spawn height: the file's torso height (the generator puts the lowest point FLOOR_OFFSET above
    # the floor), lifted if the robot would start inside the floor.
    lowest = min(
        float(data.geom_xpos[g, 2] - _geom_extent_below(model, data, g))
        for g in range(model.ngeom)
        if model.geom_bodyid[g] in token_of_body
    )
    torso_z = float(data.xpos[torso, 2])
    spawn_z = torso_z if lowest >= 0.0 else torso_z - lowest + FLOOR_OFFSET
    return Morphology(
        name=name,
        xml=xml,
        tokens=tuple(model.body(b).name for b in bodies),
        hinges=tuple(hinges),
        symmetric_limbs=_mirror_pairs(model, data, bodies),
        proprio_static=proprio,
        context=context.astype(np.float32),
        obs_padding_mask=obs_mask,
        act_padding_mask=act_mask,
        torso_height=spawn_z,
        standing_height=max(spawn_z - FLOOR_OFFSET, 0.05),
        path=path,
    )


def _geom_extent_below(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    """How far geom ``g`` reaches below its centre (world z), at the current pose."""
    size = model.geom_size[g]
    gtype = model.geom_type[g]
    if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        return float(size[0])
    if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
        axis_z = abs(data.geom_xmat[g, 8])  # z-component of the capsule axis
        return float(size[0] + size[1] * axis_z)
    return float(model.geom_rbound[g])


def _mirror_pairs(model: mujoco.MjModel, data: mujoco.MjData, bodies: Sequence[int]) -> tuple[tuple[int, int], ...]:
    """Token pairs whose body frames and geoms mirror each other across the xz-plane."""
    mirror = np.array([1.0, -1.0, 1.0])
    pairs = []
    for i, a in enumerate(bodies[1:], start=1):
        if abs(data.xpos[a, 1]) < 1e-6 and abs(data.geom_xpos[model.body_geomadr[a], 1]) < 1e-6:
            continue
        for j in range(i + 1, len(bodies)):
            b = bodies[j]
            if np.allclose(data.xpos[a] * mirror, data.xpos[b], atol=1e-4) and np.allclose(
                data.geom_xpos[model.body_geomadr[a]] * mirror, data.geom_xpos[model.body_geomadr[b]], atol=1e-4
            ):
                pairs.append((i, j))
                break
    return tuple(pairs)


def load_morphology(path: str | Path) -> Morphology:
    """Load one UNIMAL MJCF file.

    :param path: path to an ``.xml`` robot file (official unimals_100 layout or generated).
    :raises MorphologyError: the file is missing, unreadable, or not a UNIMAL robot.
    """
    path = Path(path)
    if not path.is_file():
        raise MorphologyError(f"{path}: no such MJCF file")
    # One load per file and version in a process: every env of a vectorised stage loads the same
    # robots, and each load compiles the robot, leaving ~1.9 MB of freed but unreturned heap per
    # robot behind (190 MB per env for 100 robots). Morphologies are frozen, so sharing is safe.
    stat = path.stat()
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    if key not in _LOADED:
        try:
            xml = path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise MorphologyError(f"{path}: cannot read it ({err})") from None
        _LOADED[key] = parse_morphology(xml, name=path.stem, source=str(path), path=path.resolve())
    return _LOADED[key]


#: Morphologies loaded in this process, by (resolved path, modification time, size).
_LOADED: dict[tuple[str, int, int], Morphology] = {}


def shipped_set_dir(name: str) -> Path:
    """Directory of a morphology set shipped with the package (``train`` or ``novel``)."""
    if name not in SHIPPED_SETS:
        raise MorphologyError(f"unknown morphology set '{name}'; shipped sets are {list(SHIPPED_SETS)}")
    return _DATA_DIR / name


#: The official sets, fetched into a cache by ``python -m unimal_envs.morphology fetch``
#: (:mod:`unimal_envs.morphology.official`).
OFFICIAL_SET_NAMES = tuple(OFFICIAL_SETS)
#: Named parts of the official sets: ``unimals100-val`` (10 training robots held out for choices
#: about generalisation) and ``unimals100-fit`` (the other 90).
SUBSET_NAMES = tuple(SUBSETS)


def is_set_name(name: object) -> bool:
    """Whether ``name`` names a robot set (shipped, official or a part of one) rather than a path."""
    return isinstance(name, str) and (name in SHIPPED_SETS or name in OFFICIAL_SET_NAMES or name in SUBSET_NAMES)


def set_dir(name: str) -> Path:
    """Folder of a named set: a shipped one, or an official one from the cache (a part of an
    official set lives in its parent's folder).

    :raises MorphologyError: unknown name, or an official set that is not fetched yet (the message
        gives the fetch command).
    """
    if name in SUBSET_NAMES:
        return official_set_dir(SUBSETS[name].parent)
    if name in OFFICIAL_SET_NAMES:
        return official_set_dir(name)
    return shipped_set_dir(name)


def morphology_files(morphologies: str | Path | Iterable[str | Path]) -> list[Path]:
    """Resolve the ``morphologies=`` argument of the envs to a sorted list of MJCF files.

    :param morphologies: ``"train"`` or ``"novel"`` (shipped sets), ``"unimals100-train"``,
        ``"unimals100-test"`` (97 held-out robots: the byte copies of training robots are left out)
        or ``"unimals100-mutants"`` (the official sets, once fetched), ``"unimals100-val"`` /
        ``"unimals100-fit"`` (10 training robots held out for choices, and the other 90), a
        directory in the unimals_100 layout (``DIR/xml/*.xml``) or holding ``*.xml`` directly, one
        ``.xml`` file, or a list of files and robot names (a name is looked up in the shipped sets
        and the official sets fetched on this machine).
    :raises MorphologyError: unknown set name, official set not fetched, empty directory, missing file.
    """
    if isinstance(morphologies, (str, Path)):
        if is_set_name(morphologies):
            files = morphology_files(set_dir(morphologies))
            if morphologies in SUBSET_NAMES:
                return SUBSETS[str(morphologies)].select(files)
            # a cache fetched before the byte copies were left out still holds them
            copies = OFFICIAL_SETS[morphologies].byte_copies if morphologies in OFFICIAL_SETS else {}
            return [f for f in files if f.stem not in copies]
        path = Path(morphologies)
        if path.is_dir():
            xml_dir = path / "xml" if (path / "xml").is_dir() else path
            files = sorted(xml_dir.glob("*.xml"))
            if not files:
                raise MorphologyError(f"{path}: directory holds no MJCF files (looked for {xml_dir}/*.xml)")
            return files
        if path.suffix == ".xml":
            return morphology_files([path])
        choices = f"use one of {list(SHIPPED_SETS + OFFICIAL_SET_NAMES + SUBSET_NAMES)}, a directory of MJCF files (DIR/xml/*.xml), or a list of .xml paths"
        if isinstance(morphologies, Path) or len(path.parts) > 1 or str(morphologies).startswith((".", "~")):
            # written as a path: say so, rather than calling it an unknown set name
            kind = "not a directory" if path.exists() else "no such directory"
            where = "" if path.expanduser().is_absolute() else f" (relative to {Path.cwd()})"
            raise MorphologyError(f"{kind}: {path}{where}; {choices}")
        raise MorphologyError(f"unknown morphology set '{morphologies}' (and no such directory in {Path.cwd()}); {choices}")
    files = [_robot_by_name(p) if _is_robot_name(p) else Path(p) for p in morphologies]
    if not files:
        raise MorphologyError("the list of morphology files is empty")
    missing = [str(p) for p in files if not p.is_file()]
    if missing:
        raise MorphologyError(f"no such MJCF file(s): {missing}")
    return files


def _is_robot_name(entry: str | Path) -> bool:
    """A bare robot name (``train-003``, ``floor-1409-0-3-01-15-56-55``) rather than a file path."""
    return isinstance(entry, str) and not entry.endswith(".xml") and len(Path(entry).parts) == 1 and not Path(entry).is_file()


def _robot_by_name(name: str) -> Path:
    """The MJCF file of a robot named in a shipped set or in an official set fetched on this machine.

    :raises MorphologyError: no such robot in any of them (the message lists where it looked).
    """
    searched = []
    for set_name in (*SHIPPED_SETS, *OFFICIAL_SET_NAMES):
        try:
            folder = set_dir(set_name)
        except MorphologyError:  # an official set that is not fetched here
            continue
        searched.append(set_name)
        candidate = (folder / "xml" if (folder / "xml").is_dir() else folder) / f"{name}.xml"
        if candidate.is_file():
            return candidate
    raise MorphologyError(
        f"no robot named {name!r} in the sets on this machine ({', '.join(searched)}); give an .xml path, "
        "or fetch the official sets with `python -m unimal_envs.morphology fetch`"
    )


def load_morphologies(morphologies: str | Path | Iterable[str | Path | Morphology]) -> list[Morphology]:
    """Load every robot named by ``morphologies`` (see :func:`morphology_files`); already loaded
    :class:`Morphology` objects in a list are passed through."""
    if not isinstance(morphologies, (str, Path)):
        morphologies = list(morphologies)
        if morphologies and all(isinstance(m, Morphology) for m in morphologies):
            return morphologies
    return [load_morphology(p) for p in morphology_files(morphologies)]


def read_metadata(xml_path: Path) -> dict | None:
    """The unimals_100 metadata json next to an ``xml/`` file (``DIR/metadata/<name>.json``), if any."""
    meta = xml_path.parent.parent / "metadata" / f"{xml_path.stem}.json"
    return json.loads(meta.read_text()) if meta.is_file() else None
