"""The task interface: reward, termination, task observations and the world it needs."""

from __future__ import annotations

import abc

import mujoco
import numpy as np

from unimal_envs.arenas import Arena
from unimal_envs.instructions import INSTRUCTIONS
from unimal_envs.robot import Robot

#: Control period: 4 physics substeps (robot.TIMESTEP) per action.
CONTROL_DT = 0.02


class Task(abc.ABC):
    """What the robot should do.

    A task owns its :attr:`arena`, chooses the spawn pose, adds its props (goals, objects) to the
    world, and turns a step into reward terms, a termination reason and task observations. The env
    composes it with a :class:`~unimal_envs.robot.Robot`.

    Subclasses set :attr:`name` (a key of :data:`~unimal_envs.instructions.INSTRUCTIONS`) and
    implement :meth:`make_arena` and :meth:`reward_terms`.
    """

    #: Short name used in env ids (``Unimal-<name>-v<version>``) and ``info["task"]``.
    name: str = ""
    #: The env id's version: it moves when the task's dynamics, reward or observation change, and the
    #: class docstring's Version History says what changed.
    version: int = 0
    #: Episode ends when torso height above ground <= ratio x standing height (MetaMorph 0.5).
    fall_height_ratio: float = 0.5
    #: The task observations this task fills (the other keys stay zeros); e.g. an exported
    #: single-task controller folds the encoders of the missing ones into constants.
    observation_keys: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.arena = self.make_arena()

    @property
    def instruction(self) -> str:
        """Natural-language instruction; its embedding is the ``task_embedding`` observation."""
        return INSTRUCTIONS[self.name]

    @abc.abstractmethod
    def make_arena(self) -> Arena:
        """The arena of this task (one per task instance)."""

    def spawn_pose(self, robot: Robot) -> tuple[tuple[float, float, float], tuple[float, float, float, float] | None]:
        """Torso position and orientation (w, x, y, z; ``None`` = upright) at the start of an episode."""
        return (0.0, 0.0, robot.morphology.torso_height), None

    def build(self, spec: mujoco.MjSpec) -> None:
        """Add the task's props (goals, objects) to the world spec. Default: none."""

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve ids of the task's props in the current compiled world (every episode)."""
        self.model, self.data = model, data

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        """Start an episode: sample goals and place props (call ``mj_forward`` after moving bodies)."""

    @abc.abstractmethod
    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        """Per-term rewards of the step that moved the torso from ``torso_before`` to now."""

    def termination(self, robot: Robot) -> str | None:
        """A task-specific reason to end the episode (``None`` = continue). Falls are checked by the env."""
        return None

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        """Task observations (``hfield``, ``goal``, ``object``); keys not returned are zeros."""
        return {}

    def metrics(self, robot: Robot) -> dict[str, float]:
        """Task-specific progress reported in ``info`` (e.g. distance travelled, cells visited)."""
        return {}


def to_torso_frame(robot: Robot, vector: np.ndarray) -> np.ndarray:
    """A world-frame vector expressed in the torso frame, as float32."""
    return (np.asarray(vector) @ robot.torso_xmat).astype(np.float32)


def height_map(task: Task, robot: Robot) -> np.ndarray:
    """The arena's height map around the torso, rotated by its heading."""
    from unimal_envs.arenas.heightfield import torso_yaw

    x, y, _ = robot.torso_qpos.tolist()
    heights = task.arena.height_map(x, y, torso_yaw(robot.torso_xmat))
    if heights is None:  # a task that observes "hfield" on an arena without one: a bug, not an observation
        raise TypeError(f"{type(task.arena).__name__} has no height map (task {task.name})")
    return heights
