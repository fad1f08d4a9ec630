"""One robot's worlds: a MuJoCo Warp model and data with ``W`` worlds of the single env's world.

:class:`RobotWorlds` compiles the very world :class:`~unimal_envs.env.UnimalEnv` compiles (robot at
the task's spawn pose + arena + task props, :meth:`UnimalEnv.world_spec`), puts it on the device
with ``nworld = W``, and steps, resets and reads all its worlds at once through torch views of the
Warp arrays (zero-copy). Nothing here loops over worlds.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

import mujoco
import warp as wp
import mujoco_warp as mjw

from unimal_envs import contract as C
from unimal_envs.env import UnimalEnv, compile_world
from unimal_envs.morphology.loader import MorphologyError
from unimal_envs.batched.terrain import TerrainPool

#: Physics substeps per control step, as in the single env.
SUBSTEPS = 4
#: MuJoCo's divergence threshold (mjMAXVAL): a larger |qpos| or |qvel| is a physics fault.
MAX_STATE = 1e10
#: Contacts and constraint rows allocated per world. UNIMAL robots touch the ground with at most
#: a dozen capsules (<= 4 contacts each on a height field, 4 pyramid rows per contact).
CONTACTS_PER_WORLD = 96
CONSTRAINTS_PER_WORLD = 4 * CONTACTS_PER_WORLD + 64


def _view(array: wp.array) -> torch.Tensor:
    return wp.to_torch(array)


def run_physics(groups: list[RobotWorlds], name: str) -> None:
    """Run physics program ``name`` (see :meth:`RobotWorlds.launch`) on every robot's worlds.

    On CUDA the robots' graphs run concurrently, each on its robot's stream, after the torch work
    queued so far (actions, resets) and before the torch work queued next (observations)."""
    if not groups or groups[0].stream is None:
        for group in groups:
            group.launch(name)
        return
    torch_stream = wp.stream_from_torch(torch.cuda.current_stream(groups[0].torch_device))
    ready = torch_stream.record_event()
    for group in groups:
        group.stream.wait_event(ready)
        group.launch(name)
    for group in groups:
        torch_stream.wait_stream(group.stream)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


class RobotWorlds:
    """``worlds`` copies of one robot's world on one device.

    :param env: the single env whose world (task, arena, robot) is simulated.
    :param index: the morphology's index in ``env.morphologies``.
    :param worlds: number of worlds (W).
    :param device: Warp device name (``"cpu"``, ``"cuda:0"``).
    :param pool: the task's terrain variants (``None``: no random terrain).
    """

    def __init__(self, env: UnimalEnv, index: int, worlds: int, device: str, pool: TerrainPool | None):
        spec, robot = env.world_spec(index)
        name = robot.morphology.name
        if pool is not None:
            pool.add_assets(spec)
        model = compile_world(spec, name)
        data = mujoco.MjData(model)
        robot.bind(model, data)
        self.robot, self.morphology, self.worlds = robot, robot.morphology, worlds
        self.mj_model = model
        batch = {}
        self.terrain_geom = self.variant_dataid = None
        if pool is not None and pool.hfield is not None:
            self.terrain_geom, self.variant_dataid = pool.hfield_ids(model)
            batch["geom_dataid"] = worlds
        self.obstacle_ids = np.array([model.geom(n).id for n in pool.obstacle_geoms] if pool else [], dtype=np.int64)
        if self.obstacle_ids.size:
            batch.update({field: worlds for field in ("geom_pos", "geom_size", "geom_aabb", "geom_rbound")})
        self.device = device
        with wp.ScopedDevice(device):
            try:
                self.model = mjw.put_model(model, batch_sizes=batch)
            except NotImplementedError as err:
                raise MorphologyError(f"{name}: MuJoCo Warp cannot simulate this robot's world: {err}") from None
            self.data = mjw.make_data(model, nworld=worlds, nconmax=CONTACTS_PER_WORLD, njmax=CONSTRAINTS_PER_WORLD)
        self._views()
        self._indices(model, env)
        self._graphs: dict[str, object] = {}
        self._warm: set[str] = set()
        #: On CUDA each robot's graph has its own stream, so the robots' small graphs run concurrently.
        self.stream = wp.Stream(device) if self.torch_device.type == "cuda" else None

    # ------------------------------------------------------------------ set-up
    def _views(self) -> None:
        d = self.data
        self.qpos, self.qvel, self.ctrl = _view(d.qpos), _view(d.qvel), _view(d.ctrl)
        self.time, self.qacc_warmstart = _view(d.time), _view(d.qacc_warmstart)
        self.xpos, self.xquat, self.xmat = _view(d.xpos), _view(d.xquat), _view(d.xmat)
        self.cvel, self.subtree_com, self.site_xpos = _view(d.cvel), _view(d.subtree_com), _view(d.site_xpos)
        self.torch_device = self.qpos.device
        if self.variant_dataid is not None:
            self.geom_dataid = _view(self.model.geom_dataid)
        if self.obstacle_ids.size:
            m = self.model
            self.geom_pos, self.geom_size = _view(m.geom_pos), _view(m.geom_size)
            self.geom_aabb, self.geom_rbound = _view(m.geom_aabb), _view(m.geom_rbound)

    def _indices(self, model: mujoco.MjModel, env: UnimalEnv) -> None:
        robot, dev = self.robot, self.torch_device
        n = robot.num_tokens
        self.torso = robot.torso_id
        self.bodies = torch.arange(robot.torso_id, robot.torso_id + n, device=dev)
        self.qpos_root, self.qvel_root = robot._qpos_root, robot._qvel_root
        self.robot_qpos = slice(robot._qpos_root, robot._qpos_hinges.stop)
        self.robot_qvel = slice(robot._qvel_root, robot._qvel_hinges.stop)
        self.qpos0 = torch.as_tensor(model.qpos0, dtype=torch.float32, device=dev)
        # Hinges in sensor order (token order, "x" before "y"), as Robot.proprioception reads them.
        hinges = list(robot._slot_of_hinge)
        ids = [model.joint(h).id for h in hinges]
        self.hinge_qpos = torch.as_tensor(model.jnt_qposadr[ids], device=dev)
        self.hinge_qvel = torch.as_tensor(model.jnt_dofadr[ids], device=dev)
        self.hinge_scale = torch.as_tensor(robot._hinge_scale[: robot.dof], dtype=torch.float32, device=dev)
        self.hinge_offset = torch.as_tensor(robot._hinge_offset[: robot.dof], dtype=torch.float32, device=dev)
        dof = robot.dof
        self.hinge_q_cols = torch.as_tensor(robot._hinge_targets[:dof], device=dev)
        self.hinge_v_cols = torch.as_tensor(robot._hinge_targets[dof:], device=dev)
        self.static = torch.as_tensor(robot._static, device=dev)
        self.ctrl_actuators = torch.as_tensor(robot._robot_actuators, device=dev)
        self.ctrl_slots = torch.as_tensor(robot._ctrl_slots, device=dev)
        self.fall_height = env.task.fall_height_ratio * self.morphology.standing_height
        names = [model.site(i).name for i in range(model.nsite)]
        robot_sites = [i for i, s in enumerate(names) if s.startswith(("limb/mid/", "limb/btm/", "torso"))]
        self.robot_points = torch.as_tensor(robot_sites, device=dev)
        self.points_are_sites = bool(robot_sites)
        if not robot_sites:
            self.robot_points = self.bodies
        self.box = self.box_qpos = self.box_qvel = self.faces = None
        if any(model.body(b).name == "box/1" for b in range(model.nbody)):
            self.box = model.body("box/1").id
            joint = model.joint("box/1").id
            self.box_qpos = int(model.jnt_qposadr[joint])
            self.box_qvel = int(model.jnt_dofadr[joint])
            self.faces = torch.as_tensor([model.site(f"box/face/{i}").id for i in range(6)], device=dev)

    # ------------------------------------------------------------------ physics
    def launch(self, name: str) -> None:
        """Run the physics program ``name`` (``"step"``: 4 substeps then kinematics; ``"sync"``:
        kinematics of the current qpos/qvel) on this robot's worlds, as a graph from the second
        call on (the first runs kernel by kernel: MuJoCo Warp compiles its kernels on first use,
        which a capture cannot hold). On CUDA it runs on this robot's own stream; order it with
        torch's work through :func:`run_physics`. On CPU Warp the replay is ~3x faster than
        launching kernel by kernel, with identical results."""
        fn = self._step_physics if name == "step" else self._sync_physics
        stream = self.stream
        graph = self._graphs.get(name)
        with wp.ScopedDevice(self.device):
            if graph is None and name not in self._warm:
                with wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext():
                    fn()
                self._warm.add(name)
                return
            if graph is None:
                with wp.ScopedCapture(device=self.device, stream=stream) as capture:
                    fn()
                graph = self._graphs[name] = capture.graph
            wp.capture_launch(graph, stream=stream)

    def _step_physics(self) -> None:
        for _ in range(SUBSTEPS):
            mjw.step(self.model, self.data)
        self._sync_physics()

    def _sync_physics(self) -> None:
        # As Robot.sync: positions, frames and velocities of the current qpos/qvel.
        mjw.kinematics(self.model, self.data)
        mjw.com_pos(self.model, self.data)
        mjw.com_vel(self.model, self.data)

    def apply(self, actions: torch.Tensor) -> None:
        """Write (W, 24) padded actions to the motors (MuJoCo Warp clamps them to [-1, 1])."""
        self.ctrl[:, self.ctrl_actuators] = actions[:, self.ctrl_slots]

    def faults(self) -> torch.Tensor:
        """(W,) worlds whose qpos or qvel is non-finite or beyond MuJoCo's 1e10 limit."""
        qpos, qvel = self.qpos, self.qvel
        bad = ~(torch.isfinite(qpos).all(1) & torch.isfinite(qvel).all(1))
        return bad | (qpos.abs() > MAX_STATE).any(1) | (qvel.abs() > MAX_STATE).any(1)

    def reset(self, mask: torch.Tensor, noise: float, generator: torch.Generator,
              props_qpos: tuple[int, torch.Tensor] | None = None) -> None:
        """Start new episodes in the worlds where ``mask`` (W,) is true: the spawn pose plus
        U(-noise, noise) on every robot qpos and qvel entry (as ``Robot.reset``), zero velocity
        elsewhere, time 0. ``props_qpos`` = (qpos address, (W, k) values) places a task prop.
        Run ``"sync"`` (:func:`run_physics`) afterwards."""
        w, dev = self.worlds, self.torch_device
        keep = ~mask[:, None]
        qpos = self.qpos0.expand(w, -1).clone()
        qvel = torch.zeros_like(self.qvel)
        q, v = self.robot_qpos, self.robot_qvel
        qpos[:, q] += (torch.rand((w, q.stop - q.start), generator=generator, device=dev) * 2 - 1) * noise
        qvel[:, v] = (torch.rand((w, v.stop - v.start), generator=generator, device=dev) * 2 - 1) * noise
        if props_qpos is not None:
            adr, values = props_qpos
            qpos[:, adr : adr + values.shape[1]] = values
        self.qpos.copy_(torch.where(keep, self.qpos, qpos))
        self.qvel.copy_(torch.where(keep, self.qvel, qvel))
        self.qacc_warmstart.masked_fill_(mask[:, None], 0.0)
        self.ctrl.masked_fill_(mask[:, None], 0.0)
        self.time.masked_fill_(mask, 0.0)

    def select_terrain(self, mask: torch.Tensor, variant: torch.Tensor, pool_layout: torch.Tensor | None) -> None:
        """Point the worlds where ``mask`` is true at terrain ``variant`` (W,) of the pool."""
        if self.variant_dataid is not None:
            ids = torch.as_tensor(self.variant_dataid, device=self.torch_device, dtype=self.geom_dataid.dtype)
            col = self.geom_dataid[:, self.terrain_geom]
            col.copy_(torch.where(mask, ids[variant], col))
        if self.obstacle_ids.size:
            layout = pool_layout[variant]  # (W, geoms, 13)
            g = torch.as_tensor(self.obstacle_ids, device=self.torch_device)
            m = mask[:, None, None]
            for field, cols in ((self.geom_pos, slice(0, 3)), (self.geom_size, slice(3, 6))):
                field[:, g] = torch.where(m, layout[..., cols], field[:, g])
            aabb = layout[..., 6:12].reshape(*layout.shape[:2], 2, 3)
            self.geom_aabb[:, g] = torch.where(mask[:, None, None, None], aabb, self.geom_aabb[:, g])
            self.geom_rbound[:, g] = torch.where(mask[:, None], layout[..., 12], self.geom_rbound[:, g])

    # ------------------------------------------------------------------ reading
    def torso_position(self) -> torch.Tensor:
        """(W, 3) torso world position (the free joint's qpos)."""
        return self.qpos[:, self.qpos_root : self.qpos_root + 3]

    def torso_velocity(self) -> torch.Tensor:
        """(W, 3) torso world linear velocity (the free joint's qvel)."""
        return self.qvel[:, self.qvel_root : self.qvel_root + 3]

    def torso_xmat(self) -> torch.Tensor:
        """(W, 3, 3) torso orientation (torso frame -> world)."""
        return self.xmat[:, self.torso]

    def point_velocity(self, body: int | torch.Tensor, root: int, point: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World-frame (linear velocity at ``point``, angular velocity) of ``body`` whose kinematic
        root is ``root``, as ``mj_objectVelocity(mjOBJ_XBODY, flg_local=0)``: MuJoCo's ``cvel`` is
        (angular, linear) at the root's subtree centre of mass."""
        cvel, com = self.cvel[:, body], self.subtree_com[:, root]
        if cvel.dim() == 3:
            com = com[:, None]
        angular, linear = cvel[..., :3], cvel[..., 3:]
        return linear + _cross(angular, point - com), angular

    def proprioception(self) -> torch.Tensor:
        """(W, 12, 52) ``proprioceptive`` observation, as :meth:`Robot.proprioception`."""
        n = self.robot.num_tokens
        xpos = self.xpos[:, self.bodies]
        linear, angular = self.point_velocity(self.bodies, self.torso, xpos)
        relative = xpos.clone()
        relative[..., 0] -= xpos[:, :1, 0]  # x relative to the torso; y, z absolute (MetaMorph)
        obs = self.static.expand(self.worlds, -1, -1).clone()
        obs[:, :n, :13] = torch.cat([relative, linear, angular, self.xquat[:, self.bodies]], dim=-1)
        flat = obs.view(self.worlds, -1)
        flat[:, self.hinge_q_cols] = self.qpos[:, self.hinge_qpos] * self.hinge_scale + self.hinge_offset
        flat[:, self.hinge_v_cols] = self.qvel[:, self.hinge_qvel]
        return obs

    def reach_distance(self) -> torch.Tensor:
        """(W,) smallest distance between the robot's sites (or body origins) and a box face centre."""
        points = (self.site_xpos if self.points_are_sites else self.xpos)[:, self.robot_points]
        faces = self.site_xpos[:, self.faces]
        return torch.cdist(points, faces).amin(dim=(1, 2))

    def box_state(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(W, 3) each: box position, box linear velocity (world frame, at its origin), and the box
        free joint's angular velocity ``qvel[3:6]`` (as the single env's object observation)."""
        position = self.xpos[:, self.box]
        linear, _ = self.point_velocity(self.box, self.box, position)
        return position, linear, self.qvel[:, self.box_qvel + 3 : self.box_qvel + 6]

    def memory_bytes(self) -> int:
        """Device bytes of this robot's model and data."""
        total = 0
        for obj in (self.model, self.data):
            for value in vars(obj).values():
                if isinstance(value, wp.array):
                    total += value.capacity
        return total
