"""The task interface: reward, termination, task observations and the world it needs."""

from __future__ import annotations

import mujoco
import numpy as np

from unimal_envs.arenas import Arena
from unimal_envs.instructions import INSTRUCTIONS
from unimal_envs.robot import Robot

#: Control period: 4 physics substeps (robot.TIMESTEP) per action.
CONTROL_DT = 0.02


class Task:
    """What the robot should do.

    A task chooses its arena, the spawn pose, adds its props (goals, objects) to the world, and
    turns a step into reward terms, a termination reason and task observations. The env composes
    it with a :class:`~unimal_envs.robot.Robot` and an :class:`~unimal_envs.arenas.Arena`.

    Subclasses set :attr:`name` (a key of :data:`~unimal_envs.instructions.INSTRUCTIONS`) and implement :meth:`reward_terms`.
    """

    #: Short name used in env ids (``Unimal-<name>-v0``) and ``info["task"]``.
    name: str = ""
    #: Episode ends when torso height above ground <= ratio x standing height (MetaMorph 0.5).
    fall_height_ratio: float = 0.5

    @property
    def instruction(self) -> str:
        """Natural-language instruction; its embedding is the ``task_embedding`` observation."""
        return INSTRUCTIONS[self.name]

    def make_arena(self) -> Arena:
        """A fresh arena for one env."""
        raise NotImplementedError

    def spawn_pose(self, robot: Robot) -> tuple[tuple[float, float, float], tuple[float, float, float, float] | None]:
        """Torso position and orientation (w, x, y, z; ``None`` = upright) at the start of an episode."""
        return (0.0, 0.0, robot.morphology.torso_height), None

    def build(self, spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
        """Add the task's props (goals, objects) to the world spec. Default: none."""

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve ids of the task's props in the compiled world."""

    @property
    def randomised(self) -> bool:
        """True if :meth:`build` samples something, i.e. the world is rebuilt every episode."""
        return False

    def reset(self, robot: Robot, rng: np.random.Generator) -> None:
        """Start a new episode (after the robot's state was reset and synced)."""

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        """Per-term rewards of the step that moved the torso from ``torso_before`` to now."""
        raise NotImplementedError

    def termination(self, robot: Robot) -> str | None:
        """A task-specific reason to end the episode (``None`` = continue). Falls are checked by the env."""
        return None

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        """Task observations (``hfield``, ``goal``, ``object``); keys not returned are zeros."""
        return {}
