"""Box manipulation tasks: reach a box, then push it to a goal (PushBoxIncline, ManipulateBox)."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from unimal_envs.arenas import Arena, Floor, Incline
from unimal_envs.robot import Robot
from unimal_envs.tasks.base import Task, to_torso_frame
from unimal_envs.tasks.navigation import REACH_BONUS, REACH_PROGRESS_WEIGHT, add_goal_marker

BOX = "box/1"
_XBODY = int(mujoco.mjtObj.mjOBJ_XBODY)


class _BoxTask(Task):
    """A free box and a goal marker, with DERL's two-phase manipulation reward.

    *Reach* phase: ``reach`` = 100 x (d_before - d_after), where d is the smallest distance between
    any robot site (``limb/mid``, ``limb/btm``, ``torso*``; body origins for robots without sites)
    and the box's six face centres, plus ``reached`` = +10 once, when d <= margin. *Push* phase
    (after the first reach): ``push`` = 100 x progress of the box towards the goal (horizontal) and
    ``box_at_goal`` = +10 on every step that ends with the box within the margin of the goal.
    """

    observation_keys = ("object", "goal")

    box_half_side = 0.2
    box_mass = 1.0
    margin = 0.5

    def build(self, spec: mujoco.MjSpec) -> None:
        add_goal_marker(spec)
        box = spec.worldbody.add_body(name=BOX, pos=[0.0, 0.0, 5.0])
        box.add_freejoint(name=BOX)
        s = self.box_half_side
        box.add_geom(name=BOX, type=mujoco.mjtGeom.mjGEOM_BOX, size=[s, s, s], mass=self.box_mass,
                     condim=3, rgba=[0.85, 0.65, 0.2, 1.0])
        for i, face in enumerate(np.vstack([np.eye(3), -np.eye(3)]) * s):
            box.add_site(name=f"box/face/{i}", pos=face, size=[0.01, 0.01, 0.01])

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._box = model.body(BOX).id
        self._box_qpos = data.qpos[model.jnt_qposadr[model.joint(BOX).id] :][:7]
        self._goal_site = model.site("goal").id
        faces = [model.site(f"box/face/{i}").id for i in range(6)]
        self._faces = np.array(faces)
        names = [model.site(i).name for i in range(model.nsite)]
        robot_sites = [i for i, n in enumerate(names) if n.startswith(("limb/mid/", "limb/btm/", "torso"))]
        self._robot_sites = np.array(robot_sites, dtype=np.intp)
        self._velocity = np.zeros(6)  # box (angular, linear), filled by MuJoCo
        self._rows = np.zeros((4, 3))  # the object observation before rotation into the torso frame
        self._box_xpos = data.xpos[self._box]

    def place(self, box_xyz: tuple[float, float, float], goal_xyz: tuple[float, float, float],
              quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)) -> None:
        """Put the box (at rest) and the goal marker in place, then refresh the kinematics."""
        self._box_qpos[:3] = box_xyz
        self._box_qpos[3:] = quat
        self.goal = np.asarray(goal_xyz, dtype=float)
        self.model.site_pos[self._goal_site] = self.goal
        mujoco.mj_forward(self.model, self.data)

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        self.reached = False
        self._reach_distance = self.reach_distance(robot)
        self._goal_distance = self.box_goal_distance()
        self._box_start = self.data.xpos[self._box].copy()

    def reach_distance(self, robot: Robot) -> float:
        """Smallest distance between the robot (sites, or body origins) and a box face centre."""
        data = self.data
        points = data.site_xpos[self._robot_sites] if self._robot_sites.size else data.xpos[robot._bodies]
        faces = data.site_xpos[self._faces]
        return float(np.sqrt(((points[:, None, :] - faces[None, :, :]) ** 2).sum(-1).min()))

    def box_goal_distance(self) -> float:
        box = self.data.xpos[self._box]
        return math.hypot(self.goal[0] - box[0], self.goal[1] - box[1])

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        reach = self.reach_distance(robot)
        goal = self.box_goal_distance()
        terms = {"reach": 0.0, "reached": 0.0, "push": 0.0, "box_at_goal": 0.0}
        if not self.reached:
            terms["reach"] = REACH_PROGRESS_WEIGHT * (self._reach_distance - reach)
            if reach <= self.margin:
                self.reached = True
                terms["reached"] = REACH_BONUS
        else:
            terms["push"] = REACH_PROGRESS_WEIGHT * (self._goal_distance - goal)
            terms["box_at_goal"] = REACH_BONUS if goal <= self.margin else 0.0
        self._reach_distance, self._goal_distance = reach, goal
        return terms

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        velocity, rows, torso = self._velocity, self._rows, robot.torso_qpos
        mujoco.mj_objectVelocity(self.model, self.data, _XBODY, self._box, velocity, 0)
        # Rows: box position, box velocity minus the torso's, box angular velocity, goal position.
        np.subtract(self._box_xpos, torso, out=rows[0])
        np.subtract(velocity[3:], robot.torso_velocity, out=rows[1])
        rows[2] = velocity[:3]
        np.subtract(self.goal, torso, out=rows[3])
        in_torso = to_torso_frame(robot, rows)
        return {"object": in_torso.reshape(-1), "goal": in_torso[3].copy()}

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"reached_box": float(self.reached), "box_goal_distance": self._goal_distance}


class PushBoxIncline(_BoxTask):
    """**PushBoxIncline** — push a box up a 10 degree ramp (DERL ``push_box_incline.yml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Incline`: 80 x 40 m slab rising 10 deg toward +x
    start           on the slope at x = -38 cos(10 deg) m, tilted with the slope
    props           box (0.4 m cube, 2 kg) resting on the slope at x = -35 m; goal at x = +35 m
    reward          two-phase manipulation reward (:class:`_BoxTask`), margin 0.5 m
    termination     fall: torso height above the slope <= **0.2** x standing height
    observations    ``object`` (12): box position, box velocity minus torso velocity, box angular
                    velocity, goal position, all relative to the torso and in the torso frame;
                    ``goal`` repeats the last three
    info            ``reached_box``, ``box_goal_distance``, ``box_displacement`` (along the slope)
    ==============  ===========================================================================
    """

    name = "PushBoxIncline"
    fall_height_ratio = 0.2
    box_mass = 2.0
    angle_deg = 10.0

    def make_arena(self) -> Arena:
        return Incline(self.angle_deg, half_length=40.0, half_width=20.0)

    def spawn_pose(self, robot: Robot):
        x = -38.0 * math.cos(math.radians(self.angle_deg))
        return (x, 0.0, self.arena.ground_height(x, 0.0) + robot.morphology.torso_height), self.arena.quat

    def _on_slope(self, x: float, lift: float) -> tuple[float, float, float]:
        return (x, 0.0, self.arena.ground_height(x, 0.0) + lift / math.cos(math.radians(self.angle_deg)))

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        self.place(self._on_slope(-35.0, self.box_half_side + 0.005), self._on_slope(35.0, 0.1), self.arena.quat)
        super().reset(robot, rng)

    def metrics(self, robot: Robot) -> dict[str, float]:
        moved = (self.data.xpos[self._box, 0] - self._box_start[0]) / math.cos(math.radians(self.angle_deg))
        return {**super().metrics(robot), "box_displacement": float(moved)}


class ManipulateBox(_BoxTask):
    """**ManipulateBox** — walk to a box and push it to a goal (DERL ``manipulation``, box variant).

    ==============  ===========================================================================
    arena           flat walled area x in [-2, 28] m, |y| <= 15 m
    start           torso at the origin, upright
    props           box (0.4 m cube, 1 kg) at x = min(U{15..24}, 21.8) m, |y| < 4.8 m; goal at
                    x = 21.8 m, |y| < 4.8 m
    reward          two-phase manipulation reward (:class:`_BoxTask`), margin 0.5 m
    termination     fall (0.5 x standing height)
    observations    ``object`` (12) as in PushBoxIncline; ``goal``: goal relative to the torso
    info            ``reached_box``, ``box_goal_distance``
    ==============  ===========================================================================

    Placement follows DERL's "forward" rule: 15-24 m ahead of the start, capped 6.2 m before the
    far wall (x = 21.8 m). The goal is drawn the same way from the box, so it always lands on the
    cap at x = 21.8 m: the box must mostly be pushed sideways. Kept as in the original.
    """

    name = "ManipulateBox"
    x_cap = 21.8
    y_half_range = 4.8

    def make_arena(self) -> Arena:
        return Floor(half_size=40.0, walls=(-2.0, 28.0, -15.0, 15.0))

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        box_x = min(float(rng.integers(15, 25)), self.x_cap)
        goal_x = min(box_x + float(rng.integers(15, 25)), self.x_cap)
        box_y, goal_y = rng.uniform(-self.y_half_range, self.y_half_range, size=2)
        self.place((box_x, box_y, self.box_half_side + 0.005), (goal_x, goal_y, 0.1))
        super().reset(robot, rng)
