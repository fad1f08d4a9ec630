"""UNIMAL universal-morphology benchmark as Gymnasium environments.

``import unimal_envs`` registers ``Unimal-<task>-v0`` for every task (Gymnasium 1.x has no plugin
entry points, so registration happens on import)::

    import gymnasium as gym, unimal_envs
    env = gym.make("Unimal-FT-v0", morphologies="train")
"""

from __future__ import annotations

import os

# Headless rendering by default; must be set before mujoco creates a GL context.
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402

from unimal_envs import contract  # noqa: E402
from unimal_envs.env import UnimalEnv  # noqa: E402
from unimal_envs.morphology.loader import Morphology, MorphologyError, load_morphologies, load_morphology  # noqa: E402
from unimal_envs.multitask import MultiTaskEnv  # noqa: E402
from unimal_envs.tasks import TASKS  # noqa: E402

#: Steps per episode: 1000 control steps = 20 s at 50 Hz.
MAX_EPISODE_STEPS = 1000


def env_id(task: str) -> str:
    """Gymnasium id of a task, e.g. ``env_id("FT") == "Unimal-FT-v0"``."""
    return f"Unimal-{task}-v0"


for _task in TASKS:
    gym.register(
        id=env_id(_task),
        entry_point="unimal_envs.env:UnimalEnv",
        kwargs={"task": _task},
        max_episode_steps=MAX_EPISODE_STEPS,
    )
gym.register(
    id="Unimal-MultiTask-v0",
    entry_point="unimal_envs.multitask:MultiTaskEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

__all__ = [
    "MAX_EPISODE_STEPS",
    "MultiTaskEnv",
    "Morphology",
    "MorphologyError",
    "UnimalEnv",
    "contract",
    "env_id",
    "load_morphology",
    "load_morphologies",
]
