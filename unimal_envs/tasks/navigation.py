"""Navigation tasks: reach goals, explore, escape (Patrol, PointNav, Exploration, Escape)."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from unimal_envs.arenas import Arena, Bowl, Floor
from unimal_envs.robot import Robot
from unimal_envs.tasks.base import Task, height_map, to_torso_frame

#: Reach reward (DERL ``ReachReward``): 100 x progress towards the goal (m) + 10 per step within the margin.
REACH_PROGRESS_WEIGHT = 100.0
REACH_BONUS = 10.0
SUCCESS_MARGIN = 0.5
#: Goals float 0.1 m above flat ground (MetaMorph z = 1.1 over a floor at z = 1).
GOAL_HEIGHT = 0.1


def add_goal_marker(spec: mujoco.MjSpec) -> None:
    """A visual-only goal marker (a 1 x 1 m red tile), moved by the task every episode."""
    spec.worldbody.add_site(name="goal", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.5, 0.01], rgba=[0.9, 0.2, 0.2, 0.6], pos=[0, 0, -1])


class _ReachGoal(Task):
    """Shared by goal-reaching tasks: DERL's reach reward and the ``goal`` observation."""

    observation_keys = ("goal",)
    _distance: float  # to the goal at the last step (set by the subclasses' reset)

    def build(self, spec: mujoco.MjSpec) -> None:
        add_goal_marker(spec)

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._goal_site = model.site("goal").id

    def set_goal(self, x: float, y: float) -> None:
        self.goal = np.array([x, y, GOAL_HEIGHT])
        self.model.site_pos[self._goal_site] = self.goal

    def goal_distance(self, robot: Robot) -> float:
        """Horizontal distance from the torso to the goal."""
        x, y, _ = robot.torso_qpos.tolist()
        return math.hypot(self.goal[0] - x, self.goal[1] - y)

    def reach_terms(self, robot: Robot) -> dict[str, float]:
        distance = self.goal_distance(robot)
        terms = {
            "progress": REACH_PROGRESS_WEIGHT * (self._distance - distance),
            "at_goal": REACH_BONUS if distance <= SUCCESS_MARGIN else 0.0,
        }
        self._distance = distance
        return terms

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        return {"goal": to_torso_frame(robot, self.goal - robot.torso_qpos)}


class Patrol(_ReachGoal):
    """**Patrol** — run back and forth between two goals 10 m apart (DERL ``patrol.yml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Floor`
    start           torso at (-5, 0), upright; the first goal is (+5, 0)
    reward          ``progress`` = 100 x (distance before - distance after) to the current goal
                    (m, horizontal); ``at_goal`` = +10 on a step that ends within 0.5 m of it
    goal switch     within 0.5 m the goal toggles to the other end; as in the reference, the
                    step that reaches a goal is rewarded (and observed) against that goal, and
                    the next goal is observed from the following step on
    termination     fall (0.5 x standing height)
    observations    ``goal``: current goal minus torso position, in the torso frame
    info            ``goals_reached``, ``goal_distance``
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "Patrol"
    half_length = 5.0

    def make_arena(self) -> Arena:
        return Floor(half_size=30.0)

    def spawn_pose(self, robot: Robot):
        return (-self.half_length, 0.0, robot.morphology.torso_height), None

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        self.set_goal(self.half_length, 0.0)
        self._distance = self.goal_distance(robot)
        self.goals_reached = 0
        self._observed_goal: np.ndarray | None = None

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        self._observed_goal = None
        terms = self.reach_terms(robot)
        if self._distance <= SUCCESS_MARGIN:
            self.goals_reached += 1
            # The reference builds this step's observation before toggling the goal.
            self._observed_goal = self.goal
            self.set_goal(-self.goal[0], 0.0)
            self._distance = self.goal_distance(robot)
        return terms

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        goal = self.goal if self._observed_goal is None else self._observed_goal
        return {"goal": to_torso_frame(robot, goal - robot.torso_qpos)}

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"goals_reached": self.goals_reached, "goal_distance": self._distance}


class _WalledArena:
    """The 100 x 100 m walled square of DERL's arena tasks, centred on the origin (the original
    spans x in [0, 100] with the robot at x = 50; only the origin moved)."""

    half_size = 50.0

    def make_arena(self) -> Arena:
        h = self.half_size
        return Floor(half_size=h + 10.0, walls=(-h, h, -h, h))


class PointNav(_WalledArena, _ReachGoal):
    """**PointNav** — walk to a random goal and stay there (DERL ``point_nav.yml``).

    ==============  ===========================================================================
    arena           flat 100 x 100 m square with boundary walls, centred on the origin
    start           torso at the centre, upright
    goal            uniform in x in [-43.5, 43), y in [-39.5, 39.5) (DERL's placement buffers)
    reward          ``progress`` = 100 x (distance before - distance after) (m, horizontal);
                    ``at_goal`` = +10 on every step that ends within 0.5 m (no stop on success)
    termination     fall (0.5 x standing height)
    observations    ``goal``: goal minus torso position, in the torso frame
    info            ``goal_distance``, ``steps_at_goal``
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "PointNav"

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        self.set_goal(rng.uniform(-43.5, 43.0), rng.uniform(-39.5, 39.5))
        self._distance = self.goal_distance(robot)
        self.steps_at_goal = 0

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        terms = self.reach_terms(robot)
        self.steps_at_goal += terms["at_goal"] > 0
        return terms

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"goal_distance": self._distance, "steps_at_goal": self.steps_at_goal}


class Exploration(_WalledArena, Task):
    """**Exploration** — visit as many 1 x 1 m cells as possible (DERL ``exploration.yml``).

    ==============  ===========================================================================
    arena           flat 100 x 100 m square with boundary walls, centred on the origin
    start           torso at the centre, upright; the visit grid starts empty, so the first step
                    earns +1 for the start cell (as in the reference's ``ExploreTerrainReward``)
    reward          ``new_cell`` = +1 when the torso enters a cell not visited this episode
    termination     fall (0.5 x standing height)
    observations    proprioception only
    info            ``cells_visited``
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "Exploration"
    cells = 100

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        self.visited = np.zeros((self.cells, self.cells), dtype=bool)

    def _visit(self, robot: Robot) -> bool:
        x, y, _ = robot.torso_qpos.tolist()
        col = min(max(int(math.floor(x + self.half_size)), 0), self.cells - 1)
        row = min(max(int(math.floor(y + self.half_size)), 0), self.cells - 1)
        new = not self.visited[row, col]
        self.visited[row, col] = True
        return new

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        return {"new_cell": 1.0 if self._visit(robot) else 0.0}

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"cells_visited": int(self.visited.sum())}


class Escape(Task):
    """**Escape** — climb out of a bumpy bowl (DERL ``escape.yml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Bowl`: 100 x 100 m heightfield, 0 at the centre,
                    up to 1.3 m high 25 m out, back to 0 at 50 m, with random bumps every episode
    start           torso at the centre, upright
    reward          ``radial`` = |xy| after - |xy| before (metres, *not* divided by dt, as in
                    DERL); ``escape`` = +100 on reaching |xy| >= 42 m
    termination     fall (0.5 x standing height above the bowl); ``escaped`` at |xy| >= 42 m
    observations    ``hfield``: height map of the bowl around the robot
    info            ``radius``
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "Escape"
    observation_keys = ("hfield",)
    escape_radius = 42.0
    escape_bonus = 100.0

    def make_arena(self) -> Arena:
        return Bowl(half_size=50.0, max_height=1.3)

    def spawn_pose(self, robot: Robot):
        # The bowl's centre is at most ~2 cm high; start just above it.
        return (0.0, 0.0, robot.morphology.torso_height + 0.03), None

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        radius = math.hypot(*robot.torso_qpos[:2].tolist())
        terms = {"radial": radius - math.hypot(float(torso_before[0]), float(torso_before[1]))}
        terms["escape"] = self.escape_bonus if radius >= self.escape_radius else 0.0
        return terms

    def termination(self, robot: Robot) -> str | None:
        return "escaped" if math.hypot(*robot.torso_qpos[:2].tolist()) >= self.escape_radius else None

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        return {"hfield": height_map(self, robot)}

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"radius": math.hypot(*robot.torso_qpos[:2].tolist())}
