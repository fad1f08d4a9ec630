"""Teacher labels: each state's action distribution (and critic value) by the teacher of its own task,
for numpy batches and for device tensors."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th

from sb3_divmorph.algos.distillation.observations import TASK_INDEX, ObsDict, index_obs, task_indices
from sb3_divmorph.algos.distillation.teacher import Teacher


def teacher_for(teachers: Mapping[int, Teacher], task_index: int) -> Teacher:
    """The teacher of task ``task_index``; a ``KeyError`` naming the tasks covered if there is none."""
    if task_index not in teachers:
        raise KeyError(f"no teacher for task index {task_index}; teachers cover indices {sorted(teachers)}")
    return teachers[task_index]


def teacher_labels_on_device(teachers: Mapping[int, Teacher], raw_obs: Mapping[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """:func:`teacher_labels` for device tensors: every teacher labels the whole batch and each state
    keeps its own task's label, so no step waits for the host to learn which rows belong to whom
    (a teacher's forward pass is cheap beside the student's update)."""
    tasks = raw_obs[TASK_INDEX].reshape(len(raw_obs[TASK_INDEX]), -1)[:, 0].round().long()
    mean = std = None
    for index, teacher in teachers.items():
        m, sd = teacher.action_distribution(raw_obs)
        mine = (tasks == index).unsqueeze(-1)
        mean = th.where(mine, m, th.zeros_like(m) if mean is None else mean)
        std = th.where(mine, sd, th.ones_like(sd) if std is None else std)
    assert mean is not None and std is not None
    return mean, std, tasks


def teacher_values(teachers: Mapping[int, Teacher], raw_obs: Any, tasks: Any) -> Any:
    """Each state's own task's teacher critic value (B,): numpy for numpy states, a device tensor for tensors."""
    values = None
    for index, teacher in teachers.items():
        v = teacher.value(raw_obs)
        values = th.where(th.as_tensor(tasks, device=v.device) == index, v, th.zeros_like(v) if values is None else values)
    assert values is not None
    return values if isinstance(tasks, th.Tensor) else values.cpu().numpy()


def teacher_labels(
    teachers: Mapping[int, Teacher], raw_obs: ObsDict, action_dim: int, chunk: int = 1024
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means, stds (B, A) and task indices (B,) of a batch of raw states, each by its own task's teacher."""
    tasks = task_indices(raw_obs)
    mean = np.zeros((len(tasks), action_dim), dtype=np.float32)
    std = np.ones((len(tasks), action_dim), dtype=np.float32)
    for task in np.unique(tasks):
        teacher = teacher_for(teachers, int(task))
        rows = np.flatnonzero(tasks == task)
        for start in range(0, len(rows), chunk):
            part = rows[start : start + chunk]
            m, s = teacher.action_distribution(index_obs(raw_obs, part))
            mean[part], std[part] = m.cpu().numpy(), s.cpu().numpy()
    return mean, std, tasks
