"""UNIMAL universal-morphology benchmark as Gymnasium environments.

``import unimal_envs`` registers ``Unimal-<task>-v<N>`` for every task and ``Unimal-MultiTask-v1``
(Gymnasium 1.x has no plugin entry points, so registration happens on import)::

    import gymnasium as gym, unimal_envs
    env = gym.make("Unimal-FT-v0", morphologies="train")
    unimal_envs.env_id("Obstacle")  # "Unimal-Obstacle-v1": each task's current id

A task's version moves when its dynamics, reward or observation change (its docstring's Version
History says what changed); the old id then raises Gymnasium's ``DeprecatedEnv`` naming the new one.

**One change to the process environment:** when neither ``MUJOCO_GL`` nor ``DISPLAY`` is set, the
import sets ``MUJOCO_GL=egl``. MuJoCo picks its OpenGL backend once, when ``mujoco`` is imported, and
on a machine without a display its default (GLFW) cannot render, so an ``rgb_array`` env would fail
later with an error that does not name the cause. Set ``MUJOCO_GL`` yourself (``egl``, ``osmesa``,
``glfw``) before importing to choose; with a display nothing is changed.
"""

from __future__ import annotations

import os
import re

if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: see the module docstring

import gymnasium as gym  # noqa: E402

from unimal_envs import contract  # noqa: E402
from unimal_envs.env import UnimalEnv  # noqa: E402
from unimal_envs.morphology.loader import Morphology, MorphologyError, load_morphologies, load_morphology  # noqa: E402
from unimal_envs.multitask import MultiTaskEnv  # noqa: E402
from unimal_envs.tasks import TASKS  # noqa: E402

#: Steps per episode: 1000 control steps = 20 s at 50 Hz.
MAX_EPISODE_STEPS = 1000


#: The id of the env that draws a task per episode (:class:`MultiTaskEnv`).
MULTITASK_ID = f"Unimal-MultiTask-v{MultiTaskEnv.version}"
_ID = re.compile(r"^Unimal-(?P<task>[A-Za-z]+)-v(?P<version>\d+)")


def env_id(task: str) -> str:
    """Gymnasium id of a task at its current version: ``env_id("FT") == "Unimal-FT-v0"``,
    ``env_id("Obstacle") == "Unimal-Obstacle-v1"``, ``env_id("MultiTask") == MULTITASK_ID``.

    :raises KeyError: an unknown task (the message lists the tasks).
    """
    if task == "MultiTask":
        return MULTITASK_ID
    if task not in TASKS:
        raise KeyError(f"unknown task {task!r}; tasks: {', '.join(TASKS)}")
    return f"Unimal-{task}-v{TASKS[task].version}"


def task_of(env_id_: str) -> str:
    """The task of an env id (``"Unimal-Obstacle-v1"`` or an rl-zoo entry ``"Unimal-FT-v0-metamorph"`` -> its task).

    :raises ValueError: not a ``Unimal-<task>-v<N>`` id, or an outdated version (the message names the current id).
    """
    match = _ID.match(env_id_)
    if match is None or (match["task"] not in TASKS and match["task"] != "MultiTask"):
        raise ValueError(f"{env_id_!r} is not a Unimal env id (Unimal-<task>-v<N>, tasks: {', '.join(TASKS)})")
    current = env_id(match["task"])
    if f"v{match['version']}" != current.rsplit("-", 1)[1]:
        raise ValueError(
            f"{env_id_!r} is an outdated version: the task's current id is {current!r} (its docstring's Version History says why)"
        )
    return match["task"]


for _task in TASKS:
    gym.register(
        id=env_id(_task),
        entry_point="unimal_envs.env:UnimalEnv",
        kwargs={"task": _task},
        max_episode_steps=MAX_EPISODE_STEPS,
    )
gym.register(
    id=MULTITASK_ID,
    entry_point="unimal_envs.multitask:MultiTaskEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

__all__ = [
    "MAX_EPISODE_STEPS",
    "MULTITASK_ID",
    "MultiTaskEnv",
    "Morphology",
    "MorphologyError",
    "UnimalEnv",
    "contract",
    "env_id",
    "load_morphology",
    "load_morphologies",
    "task_of",
]
