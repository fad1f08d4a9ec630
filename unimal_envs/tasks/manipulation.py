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
    """A free box and a goal marker, with DERL's manipulation reward (``tasks/manipulation.py``).

    Every step: ``reach`` = 100 x (d_before - d_after), where d is the smallest distance between
    any robot site (``limb/mid``, ``limb/btm``, ``torso*``; body origins for robots without sites)
    and the box's six face centres -- also after the box was reached, so walking away from it costs
    reward, as in the reference -- plus ``reached`` = +10 once, on the first step that ends with
    d <= margin. From that step on (the same step included): ``push`` = 100 x progress of the box
    towards the goal (horizontal) and ``box_at_goal`` = +10 on every step that ends with the box
    within the margin of the goal.

    The ``object`` observation's angular-velocity row is the box free joint's angular velocity
    (``qvel[3:6]``, MuJoCo's body frame), rotated by the torso frame like the other rows, exactly
    as the reference builds it (which treats it as a world-frame vector).
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
        box.add_geom(name=BOX, type=mujoco.mjtGeom.mjGEOM_BOX, size=[s, s, s], mass=self.box_mass, condim=3, rgba=[0.85, 0.65, 0.2, 1.0])
        for i, face in enumerate(np.vstack([np.eye(3), -np.eye(3)]) * s):
            box.add_site(name=f"box/face/{i}", pos=face, size=[0.01, 0.01, 0.01])

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._box = model.body(BOX).id
        self._box_qpos = data.qpos[model.jnt_qposadr[model.joint(BOX).id] :][:7]
        self._box_angvel = data.qvel[model.jnt_dofadr[model.joint(BOX).id] :][3:6]
        self._goal_site = model.site("goal").id
        faces = [model.site(f"box/face/{i}").id for i in range(6)]
        self._faces = np.array(faces)
        if faces != list(range(faces[0], faces[0] + 6)):
            raise RuntimeError("the box's face sites are not contiguous in the world model")
        self._face_rows = slice(faces[0], faces[0] + 6)  # a view of site_xpos, no gather
        names = [model.site(i).name for i in range(model.nsite)]
        robot_sites = [i for i, n in enumerate(names) if n.startswith(("limb/mid/", "limb/btm/", "torso"))]
        self._robot_sites = np.array(robot_sites, dtype=np.intp)
        self._reach_buffer = np.empty((max(len(robot_sites), 1), 6, 3))
        self._velocity = np.zeros(6)  # box (angular, linear), filled by MuJoCo
        self._rows = np.zeros((4, 3))  # the object observation before rotation into the torso frame
        self._box_xpos = data.xpos[self._box]

    def place(
        self,
        box_xyz: tuple[float, float, float],
        goal_xyz: tuple[float, float, float],
        quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
    ) -> None:
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
        faces = data.site_xpos[self._face_rows]
        if not self._robot_sites.size:
            points = data.xpos[robot._bodies]
            return float(np.sqrt(((points[:, None, :] - faces[None, :, :]) ** 2).sum(-1).min()))
        # Fewest numpy calls on the hot path (~7 us less than the broadcast-square-sum form).
        diff = np.subtract(data.site_xpos.take(self._robot_sites, axis=0)[:, None, :], faces, out=self._reach_buffer)
        return math.sqrt(np.einsum("ijk,ijk->ij", diff, diff).min())

    def box_goal_distance(self) -> float:
        box = self.data.xpos[self._box]
        return math.hypot(self.goal[0] - box[0], self.goal[1] - box[1])

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        reach = self.reach_distance(robot)
        goal = self.box_goal_distance()
        terms = {"reach": REACH_PROGRESS_WEIGHT * (self._reach_distance - reach), "reached": 0.0, "push": 0.0, "box_at_goal": 0.0}
        if not self.reached and reach <= self.margin:
            self.reached = True
            terms["reached"] = REACH_BONUS
        if self.reached:
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
        rows[2] = self._box_angvel  # body-frame angular velocity, as the reference reads it
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
    reward          manipulation reward (:class:`_BoxTask`), margin 0.5 m
    termination     fall: torso height above the slope <= **0.2** x standing height
    observations    ``object`` (12): box position, box velocity minus torso velocity, box angular
                    velocity, goal position, all relative to the torso and in the torso frame;
                    ``goal`` repeats the last three
    info            ``reached_box``, ``box_goal_distance``, ``box_displacement`` (along the slope)
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "PushBoxIncline"
    arena: Incline  # make_arena's (spawn_pose and reset read its quat)
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
    """**ManipulateBox** — walk to a box and push it to a goal (DERL's box manipulation, ``mvt.yml``).

    ==============  ===========================================================================
    arena           flat walled corridor x in [-3, 57] m, |y| <= 20 m (MVT's ``SIZE [30, 20, 1]``,
                    ``START_FLAT 3``)
    start           torso at the origin, upright
    props           box (0.4 m cube, 1 kg) at x = min(U{15..24}, 50.8) m, y = U[-9.8, 9.8) m;
                    goal at x = min(box x + U{15..24}, 50.5) m, y = U[-9.5, 9.5) m (0.1 m grid)
    reward          manipulation reward (:class:`_BoxTask`), margin **0.75** m
    termination     fall (0.5 x standing height)
    observations    ``object`` (12) as in PushBoxIncline; ``goal``: goal relative to the torso
    info            ``reached_box``, ``box_goal_distance``
    ==============  ===========================================================================

    Which reference: DERL *evaluated* manipulation with a ball (``manipulation_ball.yml``, a 30 x 30 m
    arena); its box variant is the evolution environment MVT (``mvt.yml``), whose constants this task
    takes: box half-side 0.2 m and mass 1 kg, success margin 0.75 m, DERL's "forward" placement
    (box 15-24 m ahead of the start, goal 15-24 m ahead of the box, both capped by the 6 m placement
    buffer before the far end and a 10 m buffer from the side walls). Kept departure: the ground is
    flat, whereas MVT lays the corridor with VT's terrain segments (the box tasks observe no
    height map, as in MVT, whose ``make_env_manipulation`` attaches none).

    Version History:

    * v0: first release.
    """

    name = "ManipulateBox"
    margin = 0.75
    start_flat, length, half_width = 3.0, 60.0, 20.0
    #: Placement caps (cells of 0.1 m): 6 m length buffer, 10 m width buffer, object half-sizes.
    box_x_cap, goal_x_cap = 50.8, 50.5
    box_y_half, goal_y_half = 9.8, 9.5

    def make_arena(self) -> Arena:
        x_min = -self.start_flat
        return Floor(half_size=70.0, walls=(x_min, x_min + self.length, -self.half_width, self.half_width))

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        box_x = min(float(rng.integers(15, 25)), self.box_x_cap)
        goal_x = min(box_x + float(rng.integers(15, 25)), self.goal_x_cap)
        # Rows of DERL's 0.1 m placement grid, uniform inside the width buffer.
        # integers() takes int bounds; round() gives the ones the float products stood for (-98..98, -95..95).
        box_y = int(rng.integers(round(-10 * self.box_y_half), round(10 * self.box_y_half))) / 10
        goal_y = int(rng.integers(round(-10 * self.goal_y_half), round(10 * self.goal_y_half))) / 10
        self.place((box_x, box_y, self.box_half_side + 0.005), (goal_x, goal_y, 0.1))
        super().reset(robot, rng)
