"""``Unimal-MultiTask-v1``: one env that draws a task per episode."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from unimal_envs import contract as C
from unimal_envs.env import UnimalEnv
from unimal_envs.morphology.loader import load_morphologies
from unimal_envs.tasks import TASKS


class MultiTaskEnv(gym.Env):
    """A UNIMAL env that draws one task (and one morphology) per episode.

    It exposes exactly the observation and action spaces of every single-task env, so one policy
    can be trained on a mix of tasks; the episode's task is in ``info["task"]`` and in the
    ``task_index`` / ``task_embedding`` observations. Each task keeps its own
    :class:`~unimal_envs.env.UnimalEnv` (and compiled worlds); the morphologies are loaded once
    and shared.

    :param tasks: task names to draw from (default: the five training tasks).
    :param morphologies: as for :class:`~unimal_envs.env.UnimalEnv`.
    :param task_probabilities: sampling probability of each task (default: uniform).
    :param render_mode: ``"rgb_array"`` or ``"human"``.
    :param env_kwargs: passed to every task's :class:`~unimal_envs.env.UnimalEnv` (e.g. ``ctrl_cost_weight``).

    Version History:

    * v1: its Obstacle episodes are ``Unimal-Obstacle-v1``'s (solid blocks).
    * v0: first release.
    """

    metadata = UnimalEnv.metadata
    #: the env id's version (``Unimal-MultiTask-v<version>``): it moves with any of its tasks'
    version = 1

    def __init__(
        self,
        tasks: Sequence[str] = C.TRAIN_TASKS,
        morphologies: str | Path | Iterable[str | Path] = "train",
        task_probabilities: Sequence[float] | None = None,
        render_mode: str | None = None,
        **env_kwargs: Any,
    ):
        tasks = list(tasks)
        unknown = [t for t in tasks if t not in TASKS]
        if not tasks or unknown:
            raise ValueError(f"tasks must be a non-empty list of {sorted(TASKS)}; unknown: {unknown}")
        if "instruction" in env_kwargs:
            raise ValueError("MultiTaskEnv uses each task's own instruction; 'instruction' is not accepted")
        if task_probabilities is not None:
            p = np.asarray(task_probabilities, dtype=float)
            if p.shape != (len(tasks),) or (p < 0).any() or not np.isclose(p.sum(), 1.0):
                raise ValueError(f"task_probabilities must be {len(tasks)} non-negative numbers summing to 1, got {task_probabilities}")
        self.tasks = tasks
        self.task_probabilities = task_probabilities
        robots = load_morphologies(morphologies)
        self.envs = {task: UnimalEnv(task, robots, render_mode=render_mode, **env_kwargs) for task in tasks}
        # the render modes this machine can serve, as each task's env lists them (headless: no "human")
        self.metadata = {**self.metadata, "render_modes": list(self.envs[tasks[0]].metadata["render_modes"])}
        self.render_mode = render_mode
        self.observation_space = C.observation_space()
        self.action_space = C.action_space()
        self.current: UnimalEnv | None = None

    @property
    def task(self) -> str:
        """Name of the current episode's task."""
        if self.current is None:
            raise AttributeError("no episode yet: call reset() first")
        return self.current.task.name

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Draw a task and a morphology and start an episode.

        :param options: ``{"task": name}`` and/or ``{"morphology": name_or_index}`` to choose them.
        """
        super().reset(seed=seed)
        options = dict(options or {})
        task = options.pop("task", None)
        if task is None:
            task = self.tasks[int(self.np_random.choice(len(self.tasks), p=self.task_probabilities))]
        elif task not in self.envs:
            raise ValueError(f"task '{task}' is not one of this env's tasks {self.tasks}")
        self.current = self.envs[task]
        return self.current.reset(seed=int(self.np_random.integers(2**31)), options=options)

    @property
    def morphologies(self) -> list:
        """The robots (shared by every task), in draw order."""
        return next(iter(self.envs.values())).morphologies

    @property
    def height_reference(self) -> str:
        """What body heights are measured from (shared by every task)."""
        return next(iter(self.envs.values())).height_reference

    @property
    def morphology_names(self) -> list[str]:
        """Names of the morphologies (shared by every task), in draw order."""
        return next(iter(self.envs.values())).morphology_names

    def set_morphology_probabilities(self, probabilities: np.ndarray | None) -> None:
        """Robot draw probabilities for every task (see :meth:`UnimalEnv.set_morphology_probabilities`)."""
        for env in self.envs.values():
            env.set_morphology_probabilities(probabilities)

    def step(self, action: np.ndarray):
        if self.current is None:
            raise RuntimeError("call reset() before step()")
        return self.current.step(action)

    def render(self):
        return self.current.render() if self.current is not None else None

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
