"""The ten tasks' rewards, terminations and task observations, for all worlds at once (torch).

Each class here is the batched twin of a task in :mod:`unimal_envs.tasks` and follows its
docstring table term by term; constants are read from the single task object so the two cannot
drift apart. State lives in (N, ...) tensors on the device; methods take a boolean world mask
where only some worlds are concerned (resets), never a Python loop over worlds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from unimal_envs import contract as C
from unimal_envs.arenas import Bowl, Incline, VariableTerrain
from unimal_envs.batched.terrain import HeightMaps
from unimal_envs.tasks import CONTROL_DT, Task
from unimal_envs.tasks.locomotion import FlatTerrain, InclineTask, _Corridor
from unimal_envs.tasks.manipulation import ManipulateBox, PushBoxIncline, _BoxTask
from unimal_envs.tasks.navigation import (
    GOAL_HEIGHT,
    REACH_BONUS,
    REACH_PROGRESS_WEIGHT,
    SUCCESS_MARGIN,
    Escape,
    Exploration,
    Patrol,
    PointNav,
)

#: Termination reasons, by code (0 = the episode goes on); ``info["termination"]`` holds the name.
REASONS = (None, "fall", "edge", "escaped", "physics_fault")
FALL, EDGE, ESCAPED, PHYSICS_FAULT = 1, 2, 3, 4


@dataclass
class Readings:
    """What the tasks read of every world after a step or a reset, (N, ...) tensors."""

    torso: torch.Tensor  #: (N, 3) torso position
    torso_velocity: torch.Tensor  #: (N, 3)
    torso_xmat: torch.Tensor  #: (N, 3, 3) torso frame -> world
    variant: torch.Tensor  #: (N,) terrain variant of each world
    box: torch.Tensor | None = None  #: (N, 3) box position (box tasks)
    box_velocity: torch.Tensor | None = None  #: (N, 3) box linear velocity
    box_angular: torch.Tensor | None = None  #: (N, 3) box free joint angular velocity (qvel[3:6])
    reach: torch.Tensor | None = None  #: (N,) robot-to-box-face distance

    def yaw(self) -> torch.Tensor:
        """(N,) torso heading, as :func:`unimal_envs.arenas.heightfield.torso_yaw`."""
        return torch.atan2(self.torso_xmat[:, 1, 0], self.torso_xmat[:, 0, 0])

    def to_torso_frame(self, vectors: torch.Tensor) -> torch.Tensor:
        """World vectors (N, 3) or (N, k, 3) in the torso frame (``vector @ xmat``)."""
        if vectors.dim() == 2:
            return torch.einsum("nj,nji->ni", vectors, self.torso_xmat)
        return torch.bmm(vectors, self.torso_xmat)


class BatchedTask:
    """The batched twin of ``task`` over ``n`` worlds.

    :param task: the single env's task object (constants, arena).
    :param n: number of worlds.
    :param device: torch device.
    :param heightmaps: the terrain pool's height maps (terrain tasks), else ``None``.
    :param generator: torch generator for goals and props.
    """

    #: Box tasks read the box (:class:`Readings` box fields).
    has_box = False

    def __init__(self, task: Task, n: int, device: torch.device, heightmaps: HeightMaps | None, generator: torch.Generator):
        self.task, self.n, self.device, self.heightmaps, self.generator = task, n, device, heightmaps, generator
        self.name = task.name
        self.edge = task.half_width - 1.0 if isinstance(task, _Corridor) else None

    def uniform(self, low: float, high: float) -> torch.Tensor:
        """(N,) draws from U(low, high)."""
        return low + (high - low) * torch.rand(self.n, generator=self.generator, device=self.device)

    def integers(self, low: int, high: int) -> torch.Tensor:
        """(N,) integer draws from [low, high), as float."""
        return torch.randint(low, high, (self.n,), generator=self.generator, device=self.device).float()

    # ------------------------------------------------------------------ episode
    def props(self, mask: torch.Tensor) -> torch.Tensor | None:
        """(N, 7) free-joint qpos of the task's prop for worlds starting an episode (box tasks)."""
        return None

    def reset(self, mask: torch.Tensor, r: Readings) -> None:
        """Start the task's episode state in the worlds where ``mask`` is true."""

    def reward_terms(self, r: Readings, torso_before: torch.Tensor) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def termination(self, r: Readings) -> torch.Tensor:
        """(N,) reason codes (:data:`REASONS`) of the task's own ends (falls are the env's)."""
        reason = torch.zeros(self.n, dtype=torch.long, device=self.device)
        if self.edge is not None:
            reason = torch.where(r.torso[:, 1].abs() >= self.edge, EDGE, reason)
        return reason

    def ground_height(self, r: Readings) -> torch.Tensor:
        """(N,) height of the ground under the torso (the fall test's reference)."""
        arena = self.task.arena
        if isinstance(arena, Incline):
            return arena.slope * r.torso[:, 0]
        if isinstance(arena, (VariableTerrain, Bowl)):  # the obstacle course's ground is flat
            assert self.heightmaps is not None  # terrain arenas always come with their height maps
            return self.heightmaps.ground_height(r.variant, r.torso[:, :2])
        return torch.zeros_like(r.torso[:, 0])

    def observations(self, r: Readings) -> dict[str, torch.Tensor]:
        if "hfield" in self.task.observation_keys:
            assert self.heightmaps is not None  # a task that observes the height map has an arena with one
            return {"hfield": self.heightmaps.height_map(r.variant, r.torso[:, :2], r.yaw())}
        return {}

    def metrics(self, r: Readings) -> dict[str, torch.Tensor]:
        return {}


class Forward(BatchedTask):
    """FT, VT, Obstacle, Incline: ``forward`` = torso speed along +x (along the slope on Incline)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        task = self.task
        self.scale = 1.0 / math.cos(math.radians(task.angle_deg)) if isinstance(task, InclineTask) else 1.0
        self.start = task.start_along_slope * math.cos(math.radians(task.angle_deg)) if isinstance(task, InclineTask) else None

    def reward_terms(self, r, torso_before):
        return {"forward": (r.torso[:, 0] - torso_before[:, 0]) / CONTROL_DT * self.scale}

    def metrics(self, r):
        out = {"x_position": r.torso[:, 0]}
        if self.start is not None:
            out["distance_along_slope"] = (r.torso[:, 0] - self.start) * self.scale
        return out


class _Reach(BatchedTask):
    """DERL's reach reward towards a per-world goal (Patrol, PointNav)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.goal = torch.zeros(self.n, 3, device=self.device)
        self.goal[:, 2] = GOAL_HEIGHT
        self.distance = torch.zeros(self.n, device=self.device)

    def goal_distance(self, r: Readings) -> torch.Tensor:
        return torch.hypot(self.goal[:, 0] - r.torso[:, 0], self.goal[:, 1] - r.torso[:, 1])

    def reach_terms(self, r: Readings) -> dict[str, torch.Tensor]:
        distance = self.goal_distance(r)
        terms = {
            "progress": REACH_PROGRESS_WEIGHT * (self.distance - distance),
            "at_goal": torch.where(distance <= SUCCESS_MARGIN, REACH_BONUS, 0.0),
        }
        self.distance = distance
        return terms

    def observations(self, r):
        return {"goal": r.to_torso_frame(self.goal - r.torso)}


class PatrolTask(_Reach):
    """Patrol: back and forth between (+-5, 0); the reaching step is observed against the old goal."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.goals_reached = torch.zeros(self.n, device=self.device)
        self.observed_goal = self.goal.clone()

    def reset(self, mask, r):
        m = mask[:, None]
        self.goal[:, 0] = torch.where(mask, self.task.half_length, self.goal[:, 0])
        self.goal[:, 1] = torch.where(mask, 0.0, self.goal[:, 1])
        self.distance = torch.where(mask, self.goal_distance(r), self.distance)
        self.goals_reached = torch.where(mask, 0.0, self.goals_reached)
        self.observed_goal = torch.where(m, self.goal, self.observed_goal)

    def reward_terms(self, r, torso_before):
        terms = self.reach_terms(r)
        reached = self.distance <= SUCCESS_MARGIN
        self.goals_reached = self.goals_reached + reached
        self.observed_goal = self.goal.clone()
        self.goal[:, 0] = torch.where(reached, -self.goal[:, 0], self.goal[:, 0])
        self.distance = torch.where(reached, self.goal_distance(r), self.distance)
        return terms

    def observations(self, r):
        return {"goal": r.to_torso_frame(self.observed_goal - r.torso)}

    def metrics(self, r):
        return {"goals_reached": self.goals_reached, "goal_distance": self.distance}


class PointNavTask(_Reach):
    """PointNav: a uniform goal per episode; +10 on every step within 0.5 m."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.steps_at_goal = torch.zeros(self.n, device=self.device)

    def reset(self, mask, r):
        self.goal[:, 0] = torch.where(mask, self.uniform(-43.5, 43.0), self.goal[:, 0])
        self.goal[:, 1] = torch.where(mask, self.uniform(-39.5, 39.5), self.goal[:, 1])
        self.distance = torch.where(mask, self.goal_distance(r), self.distance)
        self.steps_at_goal = torch.where(mask, 0.0, self.steps_at_goal)

    def reward_terms(self, r, torso_before):
        terms = self.reach_terms(r)
        self.steps_at_goal = self.steps_at_goal + (terms["at_goal"] > 0)
        return terms

    def metrics(self, r):
        return {"goal_distance": self.distance, "steps_at_goal": self.steps_at_goal}


class ExplorationTask(BatchedTask):
    """Exploration: +1 for every new 1 x 1 m cell of the 100 x 100 m arena."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        cells = self.task.cells
        self.visited = torch.zeros(self.n, cells, cells, dtype=torch.bool, device=self.device)
        self.worlds = torch.arange(self.n, device=self.device)

    def reset(self, mask, r):
        self.visited.masked_fill_(mask[:, None, None], False)

    def reward_terms(self, r, torso_before):
        cells, half = self.task.cells, self.task.half_size
        col = torch.floor(r.torso[:, 0] + half).clamp(0, cells - 1).long()
        row = torch.floor(r.torso[:, 1] + half).clamp(0, cells - 1).long()
        new = ~self.visited[self.worlds, row, col]
        self.visited[self.worlds, row, col] = True
        return {"new_cell": new.float()}

    def metrics(self, r):
        return {"cells_visited": self.visited.sum(dim=(1, 2)).float()}


class EscapeTask(BatchedTask):
    """Escape: radial progress (m) and +100 on reaching 42 m, which ends the episode."""

    def reward_terms(self, r, torso_before):
        radius = torch.hypot(r.torso[:, 0], r.torso[:, 1])
        before = torch.hypot(torso_before[:, 0], torso_before[:, 1])
        return {"radial": radius - before, "escape": torch.where(radius >= self.task.escape_radius, self.task.escape_bonus, 0.0)}

    def termination(self, r):
        radius = torch.hypot(r.torso[:, 0], r.torso[:, 1])
        return torch.where(radius >= self.task.escape_radius, ESCAPED, super().termination(r))

    def metrics(self, r):
        return {"radius": torch.hypot(r.torso[:, 0], r.torso[:, 1])}


class BoxTask(BatchedTask):
    """PushBoxIncline and ManipulateBox: reach the box (+10 once), then push it to the goal."""

    has_box = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        n, dev = self.n, self.device
        self.goal = torch.zeros(n, 3, device=dev)
        self.reached = torch.zeros(n, dtype=torch.bool, device=dev)
        self.reach_distance = torch.zeros(n, device=dev)
        self.goal_distance = torch.zeros(n, device=dev)
        self.box_start = torch.zeros(n, 3, device=dev)

    def props(self, mask):
        task, n, dev = self.task, self.n, self.device
        qpos = torch.zeros(n, 7, device=dev)
        if isinstance(task, PushBoxIncline):
            box = task._on_slope(-35.0, task.box_half_side + 0.005)
            goal = torch.tensor(task._on_slope(35.0, 0.1), device=dev).expand(n, 3)
            qpos[:, :3] = torch.tensor(box, device=dev)
            qpos[:, 3:] = torch.tensor(task.arena.quat, device=dev)
        elif isinstance(task, ManipulateBox):
            box_x = torch.clamp(self.integers(15, 25), max=task.box_x_cap)
            goal_x = torch.clamp(box_x + self.integers(15, 25), max=task.goal_x_cap)
            box_y = self.integers(int(-10 * task.box_y_half), int(10 * task.box_y_half)) / 10
            goal_y = self.integers(int(-10 * task.goal_y_half), int(10 * task.goal_y_half)) / 10
            qpos[:, 0], qpos[:, 1], qpos[:, 2], qpos[:, 3] = box_x, box_y, task.box_half_side + 0.005, 1.0
            goal = torch.stack([goal_x, goal_y, torch.full_like(goal_x, 0.1)], dim=1)
        else:
            raise TypeError(f"no batched placement for box task {task.name}")
        self.goal = torch.where(mask[:, None], goal, self.goal)
        return qpos

    def _box_goal_distance(self, r: Readings) -> torch.Tensor:
        assert r.box is not None  # a box task's readings hold the box's pose
        return torch.hypot(self.goal[:, 0] - r.box[:, 0], self.goal[:, 1] - r.box[:, 1])

    def reset(self, mask, r):
        self.reached = self.reached & ~mask
        self.reach_distance = torch.where(mask, r.reach, self.reach_distance)
        self.goal_distance = torch.where(mask, self._box_goal_distance(r), self.goal_distance)
        self.box_start = torch.where(mask[:, None], r.box, self.box_start)

    def reward_terms(self, r, torso_before):
        margin = self.task.margin
        reach, goal = r.reach, self._box_goal_distance(r)
        first = ~self.reached & (reach <= margin)
        self.reached = self.reached | first
        terms = {
            "reach": REACH_PROGRESS_WEIGHT * (self.reach_distance - reach),
            "reached": torch.where(first, REACH_BONUS, 0.0),
            "push": torch.where(self.reached, REACH_PROGRESS_WEIGHT * (self.goal_distance - goal), 0.0),
            "box_at_goal": torch.where(self.reached & (goal <= margin), REACH_BONUS, 0.0),
        }
        self.reach_distance, self.goal_distance = reach, goal
        return terms

    def observations(self, r):
        rows = torch.stack([r.box - r.torso, r.box_velocity - r.torso_velocity, r.box_angular, self.goal - r.torso], dim=1)
        in_torso = r.to_torso_frame(rows)
        return {"object": in_torso.reshape(self.n, C.OBJECT_DIM), "goal": in_torso[:, 3]}

    def metrics(self, r):
        out = {"reached_box": self.reached.float(), "box_goal_distance": self.goal_distance}
        if isinstance(self.task, PushBoxIncline):
            out["box_displacement"] = (r.box[:, 0] - self.box_start[:, 0]) / math.cos(math.radians(self.task.angle_deg))
        return out


def make_batched_task(task: Task, n: int, device: torch.device, heightmaps: HeightMaps | None, generator: torch.Generator) -> BatchedTask:
    """The batched twin of a single task object.

    :raises NotImplementedError: a task class without a batched twin (e.g. a user's own task).
    """
    for single, batched in (
        (FlatTerrain, Forward),
        (Patrol, PatrolTask),
        (PointNav, PointNavTask),
        (Exploration, ExplorationTask),
        (Escape, EscapeTask),
        (_BoxTask, BoxTask),
    ):
        if isinstance(task, single):
            return batched(task, n, device, heightmaps, generator)
    raise NotImplementedError(f"task {task.name!r} ({type(task).__name__}) has no batched implementation")
