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
world-frame linear velocity of the body-frame
origin and the world-frame angular velocity, i.e. ``mj_objectVelocity(mjOBJ_XBODY, flg_local=0)``
(= ``mj_jacBody @ qvel`` on fresh kinematics, what mujoco_py's ``body_xvelp/xvelr`` meant).
"""

from __future__ import annotations

import mujoco
import numpy as np

from unimal_envs import contract as C
from unimal_envs.morphology.loader import TORSO, Morphology

#: Physics timestep in seconds (4 substeps per control step).
TIMESTEP = 0.005
_FILTERPARENT = int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
# Body-frame origin (mjOBJ_BODY would give the centre of mass); a plain int is faster to pass.
_XBODY = int(mujoco.mjtObj.mjOBJ_XBODY)


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
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None

    # ------------------------------------------------------------------ building
    def build_spec(self, pos: tuple[float, float, float] | None = None, quat: tuple[float, ...] | None = None) -> mujoco.MjSpec:
        """A world spec holding only this robot, ready for an arena and a task to add to.

        Applies MetaMorph's loader settings: timestep 0.005, ``filterparent`` enabled, the file's
        ``<contact><exclude>`` list dropped (self-collisions are filtered by parent only).

        :param pos: torso spawn position; default ``(0, 0, torso_height)``.
        :param quat: torso spawn orientation (w, x, y, z); default identity.
        """
        spec = self.morphology.spec()
        spec.option.timestep = TIMESTEP
        spec.option.disableflags &= ~_FILTERPARENT
        spec.njmax, spec.nconmax = 1000, 200
        for exclude in list(spec.excludes):
            spec.delete(exclude)
        torso = spec.body(TORSO)
        torso.pos = pos if pos is not None else (0.0, 0.0, self.morphology.torso_height)
        if quat is not None:
            torso.quat = quat
        return spec

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
        self._ctrl_slots = np.array(
            [hinge_slots[hinge_ids.index(actuated[a])] for a in self._robot_actuators], dtype=np.intp
        )
        self._ctrl_all = len(self._robot_actuators) == model.nu
        token, slot = np.divmod(hinge_slots, C.SLOTS_PER_TOKEN)
        col = np.array([C.HINGE_SLOT_COLUMNS[s].start for s in slot], dtype=np.intp)
        # Every dynamic feature is gathered into one state vector laid out as
        # [xpos (n,3) | angular, linear velocity (n,6) | xquat (n,4) | hinge qpos | hinge qvel],
        # then scaled (qpos normalisation) and scattered into the observation with one assignment.
        n, dof = self.num_tokens, self.dof
        state = np.zeros(13 * n + 2 * dof)
        self._state = state
        self._state_xpos = state[: 3 * n].reshape(n, 3)
        self._state_velocity_rows = list(state[3 * n : 9 * n].reshape(n, 6))  # filled in place by MuJoCo
        self._state_xquat = state[9 * n : 13 * n].reshape(n, 4)
        self._state_qpos = state[13 * n : 13 * n + dof]
        self._state_qvel = state[13 * n + dof :]
        rows = np.arange(n)[:, None] * C.PROPRIO_DIM
        velocity_columns = np.r_[np.arange(C.XVELR.start, C.XVELR.stop), np.arange(C.XVELP.start, C.XVELP.stop)]
        self._state_targets = np.concatenate(
            [
                (rows + np.arange(C.XPOS.start, C.XPOS.stop)).ravel(),
                (rows + velocity_columns).ravel(),
                (rows + np.arange(C.XQUAT.start, C.XQUAT.stop)).ravel(),
                token * C.PROPRIO_DIM + col + C.HINGE_QPOS,
                token * C.PROPRIO_DIM + col + C.HINGE_QVEL,
            ]
        )
        lo, hi = model.jnt_range[hinge_ids].T
        self._state_scale = np.ones_like(state)
        self._state_offset = np.zeros_like(state)
        self._state_scale[13 * n : 13 * n + dof] = 1.0 / np.maximum(hi - lo, 1e-8)
        self._state_offset[13 * n : 13 * n + dof] = -lo * self._state_scale[13 * n : 13 * n + dof]
        self._body_ids = list(range(first, first + n))
        self._static = self.morphology.proprio_static.astype(np.float32)
        # Views into MjData stay valid for its lifetime; reading through them skips a lookup per step.
        self._xpos = data.xpos[self._bodies]
        self._xquat = data.xquat[self._bodies]
        self._hinge_qpos = data.qpos[self._qpos_hinges]
        self._hinge_qvel = data.qvel[self._qvel_hinges]

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
        model, data, state, xpos = self.model, self.data, self._state, self._state_xpos
        np.copyto(xpos, self._xpos)
        xpos[:, 0] -= xpos[0, 0]  # x relative to the torso; y, z absolute (MetaMorph)
        object_velocity = mujoco.mj_objectVelocity
        for body, row in zip(self._body_ids, self._state_velocity_rows):
            object_velocity(model, data, _XBODY, body, row, 0)
        np.copyto(self._state_xquat, self._xquat)
        np.copyto(self._state_qpos, self._hinge_qpos)
        np.copyto(self._state_qvel, self._hinge_qvel)
        np.multiply(state, self._state_scale, out=state)
        state += self._state_offset
        obs = self._static.copy()
        obs.reshape(-1)[self._state_targets] = state
        return obs
