"""The robot entity: places a UNIMAL morphology in a world and reads and drives it.

:class:`Robot` owns everything that is about the body: adding it to a world spec at a spawn
pose, mapping the padded 24-slot action onto the real motors, and computing the node-centric
``proprioceptive`` observation (spec 3.1) fast enough that the simulator, not Python, dominates
a step.

Velocity convention
-------------------
``mj_step`` leaves position-derived quantities (``xpos``, ``cvel``, ...) from the *start* of the
last substep while ``qpos``/``qvel`` are already integrated (mujoco_py observed this mixed state).
After stepping, :meth:`Robot.sync` runs ``mj_kinematics``, ``mj_comPos`` and ``mj_comVel`` so every
feature describes the same instant, the current state. Body velocities are the
world-frame linear velocity of the body-frame origin and the world-frame angular velocity, i.e.
``mj_objectVelocity(mjOBJ_XBODY, flg_local=0)`` (= ``mj_jacBody @ qvel`` on fresh kinematics,
what mujoco_py's ``body_xvelp/xvelr`` meant).

How it is read
--------------
The dynamic features come from MuJoCo sensors the robot adds to its world (``framepos``,
``framelinvel``, ``frameangvel``, ``framequat`` per body; ``jointpos``, ``jointvel`` per hinge),
so one ``mj_sensorPos`` + ``mj_sensorVel`` call computes them all in C and the observation is a
block copy plus one scatter. Sensors are disabled (``mjDSBL_SENSOR``) while ``mj_step`` runs its
four substeps and switched on only for that call; the robot file's own IMU and touch sensors
are not compiled into the world (nothing reads them).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import mujoco
import numpy as np

from unimal_envs import contract as C
from unimal_envs.morphology.loader import TORSO, Morphology

#: Physics timestep in seconds (4 substeps per control step).
TIMESTEP = 0.005
_FILTERPARENT = int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
# Body-frame origin (mjOBJ_BODY would give the centre of mass).
_XBODY = int(mujoco.mjtObj.mjOBJ_XBODY)
_JOINT = int(mujoco.mjtObj.mjOBJ_JOINT)
_SENSORS = int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
_SENSOR = mujoco.mjtSensor
#: Per token, in the order of the observation's columns 0-12 (contract XPOS, XVELP, XVELR, XQUAT).
_BODY_SENSORS = {
    "pos": _SENSOR.mjSENS_FRAMEPOS,
    "linvel": _SENSOR.mjSENS_FRAMELINVEL,
    "angvel": _SENSOR.mjSENS_FRAMEANGVEL,
    "quat": _SENSOR.mjSENS_FRAMEQUAT,
}
_HINGE_SENSORS = {"angle": _SENSOR.mjSENS_JOINTPOS, "velocity": _SENSOR.mjSENS_JOINTVEL}
# proprioception() scatters the body readings, in sensor order, into columns 0-12.
if [(c.start, c.stop) for c in (C.XPOS, C.XVELP, C.XVELR, C.XQUAT)] != [(0, 3), (3, 6), (6, 9), (9, 13)]:
    raise ImportError("unimal_envs.contract moved the body columns; update Robot's proprioception sensors")


@functools.lru_cache(maxsize=256)
def _world_xml(xml: str) -> str:
    """The robot file without its ``<contact><exclude>`` list and its sensors.

    MetaMorph drops the excludes (self-collisions are filtered by parent only). No observation
    reads the file's IMU and touch sensors, and computing them at every substep costs ~7% of a
    step, so the world does without them. Editing the text is much faster than deleting the
    elements from an MjSpec one by one, and a world is recompiled on every cache miss.
    """
    root = ET.fromstring(xml)
    for section, child in (("contact", "exclude"), ("sensor", None)):
        for parent in root.findall(section):
            for element in list(parent) if child is None else parent.findall(child):
                parent.remove(element)
    return ET.tostring(root, encoding="unicode")


@dataclass(frozen=True)
class RobotIndices:
    """Where a bound robot lives in its compiled world, and how its observation is assembled: what
    another simulator of the same world (:mod:`unimal_envs.batched`) needs to reproduce
    :meth:`Robot.apply_action` and :meth:`Robot.proprioception`."""

    #: the robot's qpos / qvel entries (root free joint, then the hinges)
    qpos: slice
    qvel: slice
    #: per hinge, in observation order: qpos and qvel addresses, angle normalisation ``q * scale + offset``
    hinge_qpos: np.ndarray
    hinge_qvel: np.ndarray
    hinge_scale: np.ndarray
    hinge_offset: np.ndarray
    #: per hinge: flat index into the (12 x 52) observation of its angle, and of its velocity
    hinge_angle_columns: np.ndarray
    hinge_velocity_columns: np.ndarray
    #: (12, 52) float32 observation template: static columns filled, dynamic ones 0
    static: np.ndarray
    #: ``ctrl[actuators[k]] = action[action_slots[k]]``
    actuators: np.ndarray
    action_slots: np.ndarray


class Robot:
    """A :class:`Morphology` in a compiled world.

    :param morphology: the robot to simulate.
    """

    def __init__(self, morphology: Morphology):
        self.morphology = morphology
        self.num_tokens = morphology.num_tokens
        self.dof = morphology.dof
        # Actuator k drives the k-th hinge in joint order; remember which action slot feeds it.
        slots, hinge_names = [], []
        for token, pair in enumerate(morphology.hinges):
            for slot, name in enumerate(pair):
                if name is not None:
                    slots.append(C.SLOTS_PER_TOKEN * token + slot)
                    hinge_names.append(name)
        self._slot_of_hinge = dict(zip(hinge_names, slots))
        self.real_slots = np.array(sorted(slots), dtype=np.intp)
        # None until bind(); typed as bound, since every method but the builders' needs a bound robot
        # (an unbound one fails as before, on None).
        self.model: mujoco.MjModel = None
        self.data: mujoco.MjData = None

    # ------------------------------------------------------------------ building
    def build_spec(self, pos: tuple[float, float, float] | None = None, quat: tuple[float, ...] | None = None) -> mujoco.MjSpec:
        """A world spec holding only this robot, ready for an arena and a task to add to.

        Applies MetaMorph's loader settings: timestep 0.005, ``filterparent`` enabled, the file's
        ``<contact><exclude>`` list dropped (self-collisions are filtered by parent only). The
        file's sensors are replaced by the proprioception sensors, which are disabled while
        stepping and evaluated once per control step by :meth:`proprioception`.

        :param pos: torso spawn position; default ``(0, 0, torso_height)``.
        :param quat: torso spawn orientation (w, x, y, z); default identity.
        """
        spec = mujoco.MjSpec.from_string(_world_xml(self.morphology.xml))
        spec.option.timestep = TIMESTEP
        spec.option.disableflags = (spec.option.disableflags & ~_FILTERPARENT) | _SENSORS
        spec.njmax, spec.nconmax = 1000, 200
        self._add_proprioception_sensors(spec)
        torso = spec.body(TORSO)
        torso.pos = pos if pos is not None else (0.0, 0.0, self.morphology.torso_height)
        if quat is not None:
            torso.quat = quat
        return spec

    def _add_proprioception_sensors(self, spec: mujoco.MjSpec) -> None:
        # sensordata then holds the whole dynamic state in one block: per token the 13 body
        # columns in observation order, then every hinge's angle, then every hinge's velocity.
        for body in self.morphology.tokens:
            for reading, kind in _BODY_SENSORS.items():
                spec.add_sensor(name=f"proprioception/{body}/{reading}", type=kind, objtype=_XBODY, objname=body)
        for reading, kind in _HINGE_SENSORS.items():
            for hinge in self._slot_of_hinge:
                spec.add_sensor(name=f"proprioception/{hinge}/{reading}", type=kind, objtype=_JOINT, objname=hinge)

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve indices into a compiled world that contains this robot."""
        self.model, self.data = model, data
        first = model.body(TORSO).id
        self.torso_id = first
        self._bodies = slice(first, first + self.num_tokens)
        names = [model.body(b).name for b in range(first, first + self.num_tokens)]
        if tuple(names) != self.morphology.tokens:
            raise RuntimeError(f"robot bodies are not contiguous in the world model: {names}")
        root = model.joint(model.body_jntadr[first])
        self._qpos_root = int(root.qposadr[0])
        self._qvel_root = int(root.dofadr[0])
        #: View of the torso's world position inside ``data.qpos`` (the free joint's first 3 entries).
        self.torso_qpos = data.qpos[self._qpos_root : self._qpos_root + 3]
        #: View of the torso's world linear velocity inside ``data.qvel`` (the free joint's first 3 dofs).
        self.torso_velocity = data.qvel[self._qvel_root : self._qvel_root + 3]
        # Hinges follow the root joint contiguously in qpos/qvel (joint order = document order).
        self._qpos_hinges = slice(self._qpos_root + 7, self._qpos_root + 7 + self.dof)
        self._qvel_hinges = slice(self._qvel_root + 6, self._qvel_root + 6 + self.dof)
        joints = [model.jnt_qposadr[model.joint(n).id] for n in self._slot_of_hinge]
        if sorted(joints) != list(range(self._qpos_hinges.start, self._qpos_hinges.stop)):
            raise RuntimeError("robot hinges are not contiguous after the root joint")
        order = np.argsort(joints)
        hinge_names = list(self._slot_of_hinge)
        hinge_slots = np.array([self._slot_of_hinge[hinge_names[i]] for i in order], dtype=np.intp)
        hinge_ids = [model.joint(hinge_names[i]).id for i in order]
        # ctrl[k] <- action[slot of actuator k's hinge]
        actuated = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
        self._robot_actuators = np.array([a for a, j in enumerate(actuated) if j in hinge_ids], dtype=np.intp)
        self._ctrl_slots = np.array([hinge_slots[hinge_ids.index(actuated[a])] for a in self._robot_actuators], dtype=np.intp)
        self._ctrl_all = len(self._robot_actuators) == model.nu
        # The proprioception sensors (see _add_proprioception_sensors) fill one block of
        # sensordata: n rows of the 13 body columns, then the hinge angles, then hinge velocities.
        n, dof = self.num_tokens, self.dof
        start = int(model.sensor(f"proprioception/{TORSO}/pos").adr[0])
        last = f"proprioception/{list(self._slot_of_hinge)[-1]}/velocity" if dof else f"proprioception/{self.morphology.tokens[-1]}/quat"
        last_sensor = model.sensor(last)
        if int(last_sensor.adr[0]) + int(last_sensor.dim[0]) != start + 13 * n + 2 * dof:
            raise RuntimeError("the robot's proprioception sensors are not one contiguous block of sensordata")
        readings = data.sensordata[start : start + 13 * n + 2 * dof]
        self._torso_relative_x = readings[: 13 * n : 13]  # body x, made relative to the torso in place
        sensor_hinges = list(self._slot_of_hinge)  # token order, "x" before "y", as the sensors
        token, slot = np.divmod(np.array([self._slot_of_hinge[h] for h in sensor_hinges], dtype=np.intp), C.SLOTS_PER_TOKEN)
        column = token * C.PROPRIO_DIM + np.array([C.HINGE_SLOT_COLUMNS[s].start for s in slot], dtype=np.intp)
        self._hinge_targets = np.concatenate([column + C.HINGE_QPOS, column + C.HINGE_QVEL])
        # Angles are normalised to [0, 1] over the joint range: (q - lo) / (hi - lo).
        lo, hi = model.jnt_range[[model.joint(h).id for h in sensor_hinges]].T
        scale = 1.0 / np.maximum(hi - lo, 1e-8)
        self._hinge_scale = np.concatenate([scale, np.ones(dof)])
        self._hinge_offset = np.concatenate([-lo * scale, np.zeros(dof)])
        # The whole sensor block in one affine map and one scatter: body readings pass unchanged,
        # hinge readings are normalised; _targets are their flat indices in the observation.
        body_targets = (np.arange(n)[:, None] * C.PROPRIO_DIM + np.arange(13)[None, :]).reshape(-1)
        self._targets = np.concatenate([body_targets, self._hinge_targets])
        self._scale = np.concatenate([np.ones(13 * n), self._hinge_scale])
        self._offset = np.concatenate([np.zeros(13 * n), self._hinge_offset])
        self._readings = readings
        self._buffer = np.empty(len(readings))
        self._static = self.morphology.proprio_static.astype(np.float32)
        self._option = model.opt
        self._flags_stepping = int(model.opt.disableflags) | _SENSORS
        self._flags_sensing = self._flags_stepping & ~_SENSORS

    def indices(self) -> RobotIndices:
        """Where this (bound) robot lives in its world; see :class:`RobotIndices`."""
        model, dof = self.model, self.dof
        ids = [model.joint(h).id for h in self._slot_of_hinge]
        return RobotIndices(
            qpos=slice(self._qpos_root, self._qpos_hinges.stop),
            qvel=slice(self._qvel_root, self._qvel_hinges.stop),
            hinge_qpos=model.jnt_qposadr[ids].copy(),
            hinge_qvel=model.jnt_dofadr[ids].copy(),
            hinge_scale=self._hinge_scale[:dof].copy(),
            hinge_offset=self._hinge_offset[:dof].copy(),
            hinge_angle_columns=self._hinge_targets[:dof].copy(),
            hinge_velocity_columns=self._hinge_targets[dof:].copy(),
            static=self._static.copy(),
            actuators=self._robot_actuators.copy(),
            action_slots=self._ctrl_slots.copy(),
        )

    # ------------------------------------------------------------------ state
    @property
    def torso_position(self) -> np.ndarray:
        """World position of the torso (a copy)."""
        return self.torso_qpos.copy()

    @property
    def torso_x(self) -> float:
        """World x of the torso (the forward coordinate of locomotion tasks)."""
        return float(self.torso_qpos[0])

    @property
    def torso_xmat(self) -> np.ndarray:
        """Torso orientation as a 3x3 rotation matrix (torso frame -> world)."""
        return self.data.xmat[self.torso_id].reshape(3, 3)

    def reset(self, rng: np.random.Generator, noise_scale: float) -> None:
        """Perturb every robot qpos and qvel entry by U(-noise, noise) (quaternion not renormalised)."""
        data = self.data
        q = slice(self._qpos_root, self._qpos_hinges.stop)
        v = slice(self._qvel_root, self._qvel_hinges.stop)
        data.qpos[q] += rng.uniform(-noise_scale, noise_scale, size=q.stop - q.start)
        data.qvel[v] += rng.uniform(-noise_scale, noise_scale, size=v.stop - v.start)

    def apply_action(self, action: np.ndarray) -> None:
        """Write the real slots of a padded action to the motors (MuJoCo clamps to [-1, 1])."""
        if self._ctrl_all:
            self.data.ctrl[:] = action[self._ctrl_slots]
        else:
            self.data.ctrl[self._robot_actuators] = action[self._ctrl_slots]

    def sync(self) -> None:
        """Make positions, frames and velocities consistent with the current qpos/qvel."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_comVel(self.model, self.data)

    def proprioception(self) -> np.ndarray:
        """The (12, 52) float32 ``proprioceptive`` observation of the current (synced) state."""
        # Sensors are off while stepping (no substep needs them) and evaluated once here.
        option, model, data = self._option, self.model, self.data
        option.disableflags = self._flags_sensing
        mujoco.mj_sensorPos(model, data)
        mujoco.mj_sensorVel(model, data)
        option.disableflags = self._flags_stepping
        x = self._torso_relative_x
        x -= x[0]  # x relative to the torso; y, z absolute (MetaMorph)
        values = np.multiply(self._readings, self._scale, out=self._buffer)
        values += self._offset
        obs = self._static.copy()
        obs.put(self._targets, values)
        return obs
