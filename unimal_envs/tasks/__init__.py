"""Tasks: reward, termination and task observations (dm_control's *task*).

``TASKS`` maps a task name (as in ``Unimal-<name>-v<version>``) to its class.
"""

from __future__ import annotations

from unimal_envs.tasks.base import CONTROL_DT, Task
from unimal_envs.tasks.locomotion import FlatTerrain, InclineTask, ObstacleTask, VariableTerrainTask
from unimal_envs.tasks.manipulation import ManipulateBox, PushBoxIncline
from unimal_envs.tasks.navigation import Escape, Exploration, Patrol, PointNav

TASKS: dict[str, type[Task]] = {
    cls.name: cls
    for cls in (
        FlatTerrain,
        VariableTerrainTask,
        InclineTask,
        ObstacleTask,
        Patrol,
        Exploration,
        Escape,
        PointNav,
        PushBoxIncline,
        ManipulateBox,
    )
}


def make_task(name: str | Task) -> Task:
    """Instantiate a task by name (``"FT"``, ...) or pass a :class:`Task` instance through.

    :raises ValueError: unknown task name (the message lists the valid ones).
    """
    if isinstance(name, Task):
        return name
    try:
        return TASKS[name]()
    except KeyError:
        raise ValueError(f"unknown task '{name}'; available tasks: {sorted(TASKS)}") from None


__all__ = ["CONTROL_DT", "TASKS", "Task", "make_task"]
