"""One robot in one world of either backend, moved by hand: the scenario tests' instrument.

A :class:`Probe` wraps world 0 of the single env (``UnimalEnv``) or of a batched env (MuJoCo Warp
on CPU Warp) behind one small interface, so a scenario -- put the torso here, push it there, step,
read the reward terms -- is written once and asserted on both backends. Moving the robot by hand
(setting the free joint's position and velocity) keeps the scenarios independent of any gait.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from unimal_envs import contract as C
from unimal_envs.arenas import Bowl, VariableTerrain
from unimal_envs.env import UnimalEnv
from unimal_envs.morphology.loader import morphology_files

BACKENDS = ("single", "batched")
#: The shipped generated robots the scenarios use (always available, unlike the official ones).
ROBOTS = morphology_files("train")[1:3]


class Probe:
    """A world of ``task`` on ``backend`` (``"single"`` or ``"batched"``) with robot ``ROBOTS[robot]``.

    :param task: task name.
    :param backend: ``"single"`` or ``"batched"``.
    :param seed: reset seed (terrain, goals, props).
    :param worlds: batched worlds per robot (the robot's first world is probed; the others run alongside).
    :param robot: which of :data:`ROBOTS` (the batched env simulates both; robot 1's model shares
        robot 0's terrain pool).
    """

    def __init__(self, task: str, backend: str, seed: int = 0, worlds: int = 2, terrain_variants: int = 2, robot: int = 0):
        self.task_name, self.backend, self._seed = task, backend, seed
        #: the probed world's row in the batch (its robot's first world)
        self.row = robot * worlds
        self.batched = backend == "batched"
        if self.batched:
            from unimal_envs.batched import make_batched_env

            self.benv = make_batched_env(
                task,
                morphologies=ROBOTS,
                worlds_per_robot=worlds,
                device="cpu",
                seed=seed,
                terrain_variants=terrain_variants,
                max_episode_steps=100_000,
            )
            self.block = self.benv.blocks[0]
            self.group = self.block.groups[robot]
            self.obs = {k: v[self.row].numpy() for k, v in self.benv.reset_tensors().items()}
            self.robot = self.group.robot
            self.standing_height = self.group.morphology.standing_height
        else:
            self.env = UnimalEnv(task, morphologies=ROBOTS[robot : robot + 1])
            self.obs, _ = self.env.reset(seed=seed)
            self.robot = self.env.robot
            self.standing_height = self.env.morphology.standing_height
        where = self.robot.indices()
        self._q, self._v = where.qpos.start, where.qvel.start
        self.fall_height_ratio = self.single_task.fall_height_ratio

    # ------------------------------------------------------------------ state
    @property
    def single_task(self):
        """The single env's task object (constants, arena) behind either backend."""
        return self.block.env.task if self.batched else self.env.task

    @property
    def torso(self) -> np.ndarray:
        """Torso position (world frame) now."""
        if self.batched:
            return self.group.qpos[0, self._q : self._q + 3].numpy().astype(float)
        return self.env.data.qpos[self._q : self._q + 3].copy()

    def place(self, xyz=None, velocity=None, quat=None, still: bool = False) -> None:
        """Move the torso to ``xyz`` (world), set its linear velocity (world) and orientation
        (w, x, y, z); ``still`` zeroes every velocity of the robot first."""
        if self.batched:
            qpos, qvel = self.group.qpos[0], self.group.qvel[0]
            if still:
                qvel[self.robot.indices().qvel] = 0.0
            if xyz is not None:
                qpos[self._q : self._q + 3] = torch.as_tensor(xyz, dtype=torch.float32)
            if quat is not None:
                qpos[self._q + 3 : self._q + 7] = torch.as_tensor(quat, dtype=torch.float32)
            if velocity is not None:
                qvel[self._v : self._v + 3] = torch.as_tensor(velocity, dtype=torch.float32)
            self.group.launch("sync")
        else:
            d = self.env.data
            if still:
                d.qvel[self.robot.indices().qvel] = 0.0
            if xyz is not None:
                d.qpos[self._q : self._q + 3] = xyz
            if quat is not None:
                d.qpos[self._q + 3 : self._q + 7] = quat
            if velocity is not None:
                d.qvel[self._v : self._v + 3] = velocity
            mujoco.mj_forward(self.env.model, d)
            self.robot.sync()

    def step(self, action=None) -> tuple[float, dict[str, float], bool, str | None]:
        """One control step of world 0 (zero action by default): (reward, reward terms, terminated,
        termination reason). A batched world that terminates starts its next episode at once."""
        action = np.zeros(C.ACTION_DIM, dtype=np.float32) if action is None else np.asarray(action, dtype=np.float32)
        if self.batched:
            from unimal_envs.batched.tasks import REASONS

            actions = torch.zeros(self.benv.num_envs, C.ACTION_DIM)
            i = self.row
            actions[i] = torch.as_tensor(action)
            _, reward, terminated, _, info = self.benv.step_tensors(actions)
            self.obs = {k: v[i].numpy() for k, v in info["final_observation"].items()}
            self.info = {k: float(v[i]) for k, v in info["metrics"].items()}
            self.info["overflow"] = int(info["overflow"][i])
            terms = {k.removeprefix("reward_"): float(v[i]) for k, v in info.items() if k.startswith("reward_")}
            return float(reward[i]), terms, bool(terminated[i]), REASONS[int(info["termination"][i])]
        self.obs, reward, terminated, _, info = self.env.step(action)
        self.info = info
        terms = {k.removeprefix("reward_"): v for k, v in info.items() if k.startswith("reward_")}
        return float(reward), terms, terminated, info.get("termination")

    def run(self, steps: int, velocity=None) -> list[tuple[float, dict[str, float], bool, str | None]]:
        """``steps`` zero-action steps; with ``velocity``, the torso's linear velocity is set to it
        before every step (a steady push)."""
        out = []
        for _ in range(steps):
            if velocity is not None:
                self.place(velocity=velocity)
            out.append(self.step())
        return out

    def carry(self, steps: int, velocity, height: float | None = None) -> list[tuple[float, dict[str, float], bool, str | None]]:
        """Move the robot by hand for ``steps`` zero-action steps: before every step the torso is
        put ``height`` m above the ground under it (default: 0.1 m below the standing height, so the
        feet brush the ground), given linear ``velocity`` and the robot's joints are stilled -- the
        robot acts as one rigid rake, and what it runs into is pushed or stops it."""
        height = self.standing_height - 0.1 if height is None else height
        out = []
        for _ in range(steps):
            x, y, _ = self.torso
            self.place((x, y, self.ground(x, y) + height), velocity=velocity, still=True)
            out.append(self.step())
        return out

    # ------------------------------------------------------------------ task objects
    @property
    def goal(self) -> np.ndarray:
        """The current goal (goal and box tasks), world frame."""
        if self.batched:
            return self.block.task.goal[self.row].numpy().astype(float)
        return np.asarray(self.env.task.goal, dtype=float)

    @property
    def box(self) -> np.ndarray:
        """The box position (box tasks)."""
        if self.batched:
            adr = self.group.box_qpos
            return self.group.qpos[0, adr : adr + 3].numpy().astype(float)
        return self.env.data.xpos[self.env.task._box].copy()

    def ground(self, x: float, y: float) -> float:
        """Ground height at (x, y): on terrain (VT, Escape) from the arena's height grid, the same
        numbers the height-map observation is made of (world 0's terrain variant on the batched
        backend); elsewhere the arena's own surface."""
        arena = self.single_task.arena
        if not isinstance(arena, (VariableTerrain, Bowl)):
            return float(arena.ground_height(x, y))
        if self.batched:
            maps = self.block.heightmaps
            return float(maps.ground_height(self.block.variant[self.row : self.row + 1], torch.tensor([[x, y]], dtype=torch.float32))[0])
        return float(arena.grid.height(x, y))

    def redraw(self) -> None:
        """A new episode on other terrain: the single env resets with the next seed; batched world 0
        starts episodes until the pool gives it another variant."""
        self._seed += 1
        if not self.batched:
            self.obs, _ = self.env.reset(seed=self._seed)
            return
        old = int(self.block.variant[self.row])
        mask = torch.zeros(self.block.n, dtype=torch.bool)
        mask[self.row] = True
        for _ in range(50):
            self.block.reset(mask, self.benv.reset_noise_scale)
            if int(self.block.variant[self.row]) != old:
                return
        raise AssertionError("the terrain pool never gave world 0 another variant")

    def blocks(self) -> np.ndarray:
        """(count, 6) world 0's obstacle blocks: centre and half-sizes (parked ones at z < 0)."""
        if self.batched:
            return self.block.layout[self.block.variant[self.row]].numpy().astype(float)
        return self.env.arena.layout.copy()

    def lowest_robot_point(self) -> float:
        """z of the lowest point of the robot's collision geoms (capsules and spheres), now."""
        if self.batched:
            import warp as wp

            xpos = wp.to_torch(self.group.data.geom_xpos)[0].numpy()
            xmat = wp.to_torch(self.group.data.geom_xmat)[0].numpy()
        else:
            xpos, xmat = self.env.data.geom_xpos, self.env.data.geom_xmat.reshape(-1, 3, 3)
        model = self.group.mj_model if self.batched else self.env.model
        lowest = np.inf
        for g in range(model.ngeom):
            if model.body_rootid[model.geom_bodyid[g]] != self.robot.torso_id:
                continue
            radius = model.geom_size[g, 0]
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
                axis = xmat[g].reshape(3, 3)[:, 2] * model.geom_size[g, 1]
                lowest = min(lowest, xpos[g, 2] - abs(axis[2]) - radius)
            elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
                lowest = min(lowest, xpos[g, 2] - radius)
        return float(lowest)
