"""One robot's worlds: a MuJoCo Warp model and data with ``W`` worlds of the single env's world.

:class:`RobotWorlds` compiles the very world :class:`~unimal_envs.env.UnimalEnv` compiles (robot at
the task's spawn pose + arena + task props, :meth:`UnimalEnv.world_spec`), puts it on the device
with ``nworld = W``, and steps, resets and reads all its worlds at once. A control step is one
program per robot, captured as a graph: the actions are gathered onto the motors, four physics
substeps run, kinematics are refreshed (as ``Robot.sync``), and one Warp kernel writes every
world's ``proprioceptive`` observation and the few numbers the tasks read (:data:`READINGS`) into
rows of the batch's torch buffers (zero-copy views). Nothing here loops over worlds in Python, and
per step Python does one graph launch per robot.
"""

from __future__ import annotations

import contextlib

import mujoco
import mujoco_warp as mjw
import numpy as np
import torch
import warp as wp

from unimal_envs import contract as C
from unimal_envs.batched.terrain import TerrainPool
from unimal_envs.env import UnimalEnv, compile_world
from unimal_envs.morphology.loader import MorphologyError

#: Physics substeps per control step, as in the single env.
SUBSTEPS = 4
#: MuJoCo's divergence threshold (mjMAXVAL): a larger |qpos| or |qvel| is a physics fault.
MAX_STATE = 1e10
#: Contacts and constraint rows allocated per world. UNIMAL robots touch the ground with at most
#: a dozen capsules (<= 4 contacts each on a height field, 4 pyramid rows per contact).
CONTACTS_PER_WORLD = 96
CONSTRAINTS_PER_WORLD = 4 * CONTACTS_PER_WORLD + 64


#: MuJoCo Warp's capacity overflows (``data.overflow`` bits) that silently drop contacts or
#: constraint rows: a world that hits one is simulated with less than its physics. Solver
#: iteration limits (also flagged there) are not capacity problems and are not counted.
OVERFLOWS = {
    kind.name: int(kind)
    for kind in (
        mjw.OverflowType.NEFC,
        mjw.OverflowType.NJMAX_NNZ,
        mjw.OverflowType.BROADPHASE,
        mjw.OverflowType.NARROWPHASE,
        mjw.OverflowType.CCD,
        mjw.OverflowType.HFIELD,
        mjw.OverflowType.NVMAX,
        mjw.OverflowType.EPA_HORIZON,
    )
}
OVERFLOW_MASK = sum(OVERFLOWS.values())


#: Columns of the per-world readings buffer the kernel fills (see :class:`~unimal_envs.batched.tasks.Readings`).
READINGS: dict[str, slice | int] = {
    "torso": slice(0, 3),
    "torso_velocity": slice(3, 6),
    "torso_xmat": slice(6, 15),
    "fault": 15,
    "box": slice(16, 19),
    "box_velocity": slice(19, 22),
    "box_angular": slice(22, 25),
    "reach": 25,
}
N_READINGS = 26
_PROPRIO = C.MAX_TOKENS * C.PROPRIO_DIM


@wp.kernel(enable_backward=False)
def _apply_actions(
    actions: wp.array2d(dtype=float), actuators: wp.array(dtype=int), slots: wp.array(dtype=int), ctrl: wp.array2d(dtype=float)
):
    world, k = wp.tid()  # type: ignore[misc]  # a 2-D launch; Warp types tid() as any of 1 to 4 indices
    ctrl[world, actuators[k]] = actions[world, slots[k]]


@wp.kernel(enable_backward=False)
def _read_worlds(
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    xpos: wp.array2d(dtype=wp.vec3),
    xquat: wp.array2d(dtype=wp.quat),
    xmat: wp.array2d(dtype=wp.mat33),
    cvel: wp.array2d(dtype=wp.spatial_vector),
    subtree_com: wp.array2d(dtype=wp.vec3),
    site_xpos: wp.array2d(dtype=wp.vec3),
    torso: int,
    n_tokens: int,
    qpos_root: int,
    qvel_root: int,
    hinge_qpos: wp.array(dtype=int),
    hinge_qvel: wp.array(dtype=int),
    hinge_scale: wp.array(dtype=float),
    hinge_offset: wp.array(dtype=float),
    hinge_q_column: wp.array(dtype=int),
    hinge_v_column: wp.array(dtype=int),
    static_features: wp.array(dtype=float),
    box: int,
    box_qvel: int,
    points: wp.array(dtype=int),
    points_are_sites: int,
    faces: wp.array(dtype=int),
    proprio: wp.array2d(dtype=float),
    readings: wp.array2d(dtype=float),
):
    """One thread per world: the proprioceptive observation (as ``Robot.proprioception``) and the readings."""
    world = wp.tid()
    for k in range(static_features.shape[0]):
        proprio[world, k] = static_features[k]
    com = subtree_com[world, torso]
    torso_x = xpos[world, torso][0]
    for token in range(n_tokens):
        body = torso + token
        position = xpos[world, body]
        velocity = cvel[world, body]  # (angular, linear) at the root's subtree centre of mass
        angular = wp.vec3(velocity[0], velocity[1], velocity[2])
        linear = wp.vec3(velocity[3], velocity[4], velocity[5]) + wp.cross(angular, position - com)
        quat = xquat[world, body]
        row = token * 52
        proprio[world, row + 0] = position[0] - torso_x  # x relative to the torso; y, z absolute
        proprio[world, row + 1] = position[1]
        proprio[world, row + 2] = position[2]
        for i in range(3):
            proprio[world, row + 3 + i] = linear[i]
            proprio[world, row + 6 + i] = angular[i]
        for i in range(4):
            proprio[world, row + 9 + i] = quat[i]
    for h in range(hinge_qpos.shape[0]):
        proprio[world, hinge_q_column[h]] = qpos[world, hinge_qpos[h]] * hinge_scale[h] + hinge_offset[h]
        proprio[world, hinge_v_column[h]] = qvel[world, hinge_qvel[h]]
    rotation = xmat[world, torso]
    for i in range(3):
        readings[world, i] = qpos[world, qpos_root + i]
        readings[world, 3 + i] = qvel[world, qvel_root + i]
        for j in range(3):
            readings[world, 6 + 3 * i + j] = rotation[i, j]
    fault = float(0.0)  # noqa: UP018  (Warp: float() declares a variable the loops below may assign; a bare literal is a constant)
    for i in range(qpos.shape[1]):
        if not wp.isfinite(qpos[world, i]) or wp.abs(qpos[world, i]) > 1.0e10:
            fault = 1.0
    for i in range(qvel.shape[1]):
        if not wp.isfinite(qvel[world, i]) or wp.abs(qvel[world, i]) > 1.0e10:
            fault = 1.0
    readings[world, 15] = fault
    if box >= 0:
        box_position = xpos[world, box]
        box_velocity = cvel[world, box]
        box_angular = wp.vec3(box_velocity[0], box_velocity[1], box_velocity[2])
        box_linear = wp.vec3(box_velocity[3], box_velocity[4], box_velocity[5]) + wp.cross(
            box_angular, box_position - subtree_com[world, box]
        )
        nearest = float(1.0e30)  # noqa: UP018  (Warp: a variable the loop below assigns, as for fault above)
        for p in range(points.shape[0]):
            point = xpos[world, points[p]]
            if points_are_sites != 0:
                point = site_xpos[world, points[p]]
            for f in range(faces.shape[0]):
                nearest = wp.min(nearest, wp.length(point - site_xpos[world, faces[f]]))
        for i in range(3):
            readings[world, 16 + i] = box_position[i]
            readings[world, 19 + i] = box_linear[i]
            readings[world, 22 + i] = qvel[world, box_qvel + 3 + i]
        readings[world, 25] = nearest


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


class RobotWorlds:
    """``worlds`` copies of one robot's world on one device.

    :param env: the single env whose world (task, arena, robot) is simulated.
    :param index: the morphology's index in ``env.morphologies``.
    :param worlds: number of worlds (W).
    :param device: Warp device name (``"cpu"``, ``"cuda:0"``).
    :param pool: the task's terrain variants (``None``: no random terrain).
    :param terrain_from: another robot's worlds of the same task whose height fields these worlds
        read (``None``: this robot's model holds the pool's height fields). A pool of height fields
        is the same for every robot, so one copy on the device serves a whole task: the other
        robots' models are compiled with the arena's own height field only and then pointed at the
        first robot's height-field arrays (the arena geometry, and so every address, is the same).
    """

    def __init__(
        self, env: UnimalEnv, index: int, worlds: int, device: str, pool: TerrainPool | None, terrain_from: RobotWorlds | None = None
    ):
        spec, robot = env.world_spec(index)
        name = robot.morphology.name
        shares_terrain = terrain_from is not None and pool is not None and pool.hfield is not None
        if pool is not None and not shares_terrain:
            pool.add_assets(spec)
        model = compile_world(spec, name)
        data = mujoco.MjData(model)
        robot.bind(model, data)
        self.robot, self.morphology, self.worlds = robot, robot.morphology, worlds
        self.mj_model = model
        batch = {}
        self.terrain_geom = self.variant_dataid = None
        if shares_terrain:
            if model.nhfield != 1:
                raise MorphologyError(f"{name}: a robot with height fields of its own cannot share its task's terrain pool")
            self.terrain_geom, self.variant_dataid = terrain_from.terrain_geom, terrain_from.variant_dataid
            batch["geom_dataid"] = worlds
        elif pool is not None and pool.hfield is not None:
            self.terrain_geom, self.variant_dataid = pool.hfield_ids(model)
            batch["geom_dataid"] = worlds
        blocks = pool.obstacle_layout.shape[1] if pool is not None and pool.obstacle_layout is not None else 0
        #: The obstacle blocks' geoms and mocap bodies (see ObstacleCourse), empty without blocks.
        self.obstacle_ids = np.array([model.geom(f"obstacle/{i}").id for i in range(blocks)], dtype=np.int64)
        self.obstacle_mocap = np.array([model.body_mocapid[model.body(f"obstacle/{i}").id] for i in range(blocks)], dtype=np.int64)
        if self.obstacle_ids.size:
            batch.update({field: worlds for field in ("geom_size", "geom_aabb", "geom_rbound")})
        self.device = device
        with wp.ScopedDevice(device):
            try:
                self.model = mjw.put_model(model, batch_sizes=batch)
            except NotImplementedError as err:
                raise MorphologyError(f"{name}: MuJoCo Warp cannot simulate this robot's world: {err}") from None
            self.data = mjw.make_data(model, nworld=worlds, nconmax=CONTACTS_PER_WORLD, njmax=CONSTRAINTS_PER_WORLD)
        if shares_terrain:  # before any kernel runs or graph is captured
            for field in ("hfield_size", "hfield_nrow", "hfield_ncol", "hfield_adr", "hfield_data"):
                setattr(self.model, field, getattr(terrain_from.model, field))
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
        #: (W,) MuJoCo Warp's overflow bits per world (sticky until cleared; see OVERFLOWS)
        self.overflow = _view(d.overflow)
        self.torch_device = self.qpos.device
        if self.variant_dataid is not None:
            self.geom_dataid = _view(self.model.geom_dataid)
        if self.obstacle_ids.size:
            m = self.model
            self.mocap_pos, self.geom_size = _view(d.mocap_pos), _view(m.geom_size)
            self.geom_aabb, self.geom_rbound = _view(m.geom_aabb), _view(m.geom_rbound)

    def _indices(self, model: mujoco.MjModel, env: UnimalEnv) -> None:
        robot, dev = self.robot, self.torch_device
        self.torso = robot.torso_id
        where = robot.indices()
        self.robot_qpos, self.robot_qvel = where.qpos, where.qvel
        self.qpos0 = torch.as_tensor(model.qpos0, dtype=torch.float32, device=dev)
        self.fall_height = env.task.fall_height_ratio * self.morphology.standing_height

        def ints(values) -> wp.array:
            return wp.array(np.asarray(values, dtype=np.int32).reshape(-1), dtype=wp.int32, device=self.device)

        def floats(values) -> wp.array:
            return wp.array(np.asarray(values, dtype=np.float32).reshape(-1), dtype=wp.float32, device=self.device)

        names = [model.site(i).name for i in range(model.nsite)]
        sites = [i for i, name in enumerate(names) if name.startswith(("limb/mid/", "limb/btm/", "torso"))]
        self.box = self.box_qpos = None
        box_qvel, faces = -1, []
        if "box/1" in [model.body(b).name for b in range(model.nbody)]:
            self.box = model.body("box/1").id
            joint = model.joint("box/1").id
            self.box_qpos, box_qvel = int(model.jnt_qposadr[joint]), int(model.jnt_dofadr[joint])
            faces = [model.site(f"box/face/{i}").id for i in range(6)]
        bodies = range(robot.torso_id, robot.torso_id + robot.num_tokens)
        self._actuators, self._slots = ints(where.actuators), ints(where.action_slots)
        # The readout kernel's constant inputs, in its argument order after the data arrays.
        self._read_inputs = [
            robot.torso_id,
            robot.num_tokens,
            where.qpos.start,
            where.qvel.start,
            ints(where.hinge_qpos),
            ints(where.hinge_qvel),
            floats(where.hinge_scale),
            floats(where.hinge_offset),
            ints(where.hinge_angle_columns),
            ints(where.hinge_velocity_columns),
            floats(where.static),
            -1 if self.box is None else self.box,
            box_qvel,
            ints(sites or list(bodies)),
            int(bool(sites)),
            ints(faces),
        ]

    def bind_buffers(self, actions: torch.Tensor, proprio: torch.Tensor, readings: torch.Tensor) -> None:
        """Rows of the batch's buffers this robot's programs read (``actions``, (W, 24)) and write
        (``proprio``, (W, 12, 52); ``readings``, (W, :data:`N_READINGS`)); contiguous torch views."""
        self._actions = wp.from_torch(actions)
        self._proprio = wp.from_torch(proprio.view(self.worlds, _PROPRIO))
        self._readings = wp.from_torch(readings)

    # ------------------------------------------------------------------ physics
    def launch(self, name: str) -> None:
        """Run the physics program ``name`` (``"step"``: 4 substeps then kinematics; ``"sync"``:
        kinematics of the current qpos/qvel) on this robot's worlds, as a graph from the second
        call on (the first runs kernel by kernel: MuJoCo Warp compiles its kernels on first use,
        which a capture cannot hold). On CUDA it runs on this robot's own stream; order it with
        torch's work through :func:`run_physics`. On CPU Warp the replay is ~3x faster than
        launching kernel by kernel, with identical results."""
        fn = self._step_physics if name == "step" else self._sync_physics  # "sync" after a reset
        stream = self.stream
        graph = self._graphs.get(name)
        with wp.ScopedDevice(self.device):
            if graph is None and name not in self._warm:
                with wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext():
                    fn()
                self._warm.add(name)
                return
            if graph is None:
                # Warp launches on the device's current stream, not on the one being captured: make
                # the robot's stream current, or a CUDA capture records nothing and replays nothing.
                with wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext():
                    with wp.ScopedCapture(device=self.device, stream=stream) as capture:
                        fn()
                graph = self._graphs[name] = capture.graph
            wp.capture_launch(graph, stream=stream)

    def _step_physics(self) -> None:
        d = self.data
        wp.launch(
            _apply_actions, dim=(self.worlds, len(self._slots)), inputs=[self._actions, self._actuators, self._slots], outputs=[d.ctrl]
        )
        for _ in range(SUBSTEPS):
            mjw.step(self.model, d)
        self._sync_physics()

    def _sync_physics(self) -> None:
        # As Robot.sync: positions, frames and velocities of the current qpos/qvel; then the readout.
        m, d = self.model, self.data
        mjw.kinematics(m, d)
        mjw.com_pos(m, d)
        mjw.com_vel(m, d)
        wp.launch(
            _read_worlds,
            dim=self.worlds,
            inputs=[d.qpos, d.qvel, d.xpos, d.xquat, d.xmat, d.cvel, d.subtree_com, d.site_xpos, *self._read_inputs],
            outputs=[self._proprio, self._readings],
        )

    def reset(
        self, mask: torch.Tensor, noise: float, generator: torch.Generator, props_qpos: tuple[int, torch.Tensor] | None = None
    ) -> None:
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
        if not hasattr(self, "_terrain_indices"):  # on the device once, not copied at every reset
            self._terrain_indices = (
                torch.as_tensor(self.variant_dataid, device=self.torch_device, dtype=self.geom_dataid.dtype)
                if self.variant_dataid is not None
                else None,
                torch.as_tensor(self.obstacle_ids, device=self.torch_device),
                torch.as_tensor(self.obstacle_mocap, device=self.torch_device),
            )
        ids, g, b = self._terrain_indices
        if self.variant_dataid is not None:
            col = self.geom_dataid[:, self.terrain_geom]
            col.copy_(torch.where(mask, ids[variant], col))
        if self.obstacle_ids.size:
            # As apply_block_layout does in the single env: mocap poses, sizes, collision bounds.
            layout = pool_layout[variant]  # (W, blocks, 6): centre, half-size
            m = mask[:, None, None]
            half = layout[..., 3:]
            self.mocap_pos[:, b] = torch.where(m, layout[..., :3], self.mocap_pos[:, b])
            self.geom_size[:, g] = torch.where(m, half, self.geom_size[:, g])
            aabb = torch.stack([torch.zeros_like(half), half], dim=2)  # (W, blocks, 2, 3): centre offset, half-size
            self.geom_aabb[:, g] = torch.where(mask[:, None, None, None], aabb, self.geom_aabb[:, g])
            self.geom_rbound[:, g] = torch.where(mask[:, None], half.norm(dim=-1), self.geom_rbound[:, g])
