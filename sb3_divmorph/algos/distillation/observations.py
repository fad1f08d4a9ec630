"""Raw observation batches as distillation handles them: a dict of arrays, its rows, each state's task."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

#: Observation key holding the index of the episode's task in ``unimal_envs.contract.TASK_NAMES``.
TASK_INDEX = "task_index"

ObsDict = dict[str, np.ndarray]


def index_obs(obs: ObsDict, index: np.ndarray | slice) -> ObsDict:
    """Rows ``index`` of every key of a batched observation dict."""
    return {key: value[index] for key, value in obs.items()}


def task_indices(raw_obs: ObsDict) -> np.ndarray:
    """Each state's task index (B,), read from the ``task_index`` observation of a batch of raw states."""
    if TASK_INDEX not in raw_obs:
        raise KeyError(f"distillation needs the {TASK_INDEX!r} observation to pick each state's teacher")
    return np.rint(raw_obs[TASK_INDEX].reshape(len(raw_obs[TASK_INDEX]), -1)[:, 0]).astype(np.int64)


def to_numpy(value: Any) -> np.ndarray:
    """``value`` as a numpy array: a tensor copied to the host, an array as it is."""
    return value.cpu().numpy() if isinstance(value, th.Tensor) else value
