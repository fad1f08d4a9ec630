"""DAgger's aggregated dataset: raw states with their teacher labels, bounded, in numpy or on the device."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from sb3_divmorph.algos.distillation.observations import ObsDict, index_obs, to_numpy


def _zeros(like: Any, shape: tuple[int, ...], dtype: Any = None) -> Any:
    """Zeros of ``shape``: a tensor on ``like``'s device when ``like`` is a tensor, else numpy."""
    if isinstance(like, th.Tensor):
        torch_dtype = {np.float32: th.float32, np.int64: th.int64}.get(dtype, like.dtype)
        return th.zeros(shape, dtype=torch_dtype, device=like.device)
    return np.zeros(shape, dtype=dtype or like.dtype)


class DistillationDataset:
    """DAgger's aggregated dataset, bounded: raw observations with their teacher labels (FIFO ring).

    :param capacity: most states kept; the oldest are overwritten.
    """

    def __init__(self, capacity: int):
        if capacity <= 0:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.capacity = capacity
        self.obs: ObsDict = {}
        self.mean = self.std = self.task = None
        #: the teachers' critic values of the states (only when a student's critic is distilled too)
        self.value: Any = None
        self.size = 0
        self._next = 0

    def add(self, obs: ObsDict, mean: np.ndarray, std: np.ndarray, task: np.ndarray, critic_value: Any = None) -> None:
        """Store a batch of states and labels: numpy arrays, or torch tensors (the storage is then
        made on their device, and stays there); ``critic_value``: the teachers' critic values, if kept."""
        n = len(task)
        if not self.obs:
            self.obs = {k: _zeros(v, (self.capacity, *v.shape[1:])) for k, v in obs.items()}
            self.mean = _zeros(mean, (self.capacity, mean.shape[1]), np.float32)
            self.std = _zeros(mean, (self.capacity, mean.shape[1]), np.float32)
            self.task = _zeros(task, (self.capacity,), np.int64)
        if isinstance(self.task, th.Tensor):
            rows = (self._next + th.arange(n, device=self.task.device)) % self.capacity
        else:
            rows = (self._next + np.arange(n)) % self.capacity
        for key, value in obs.items():
            self.obs[key][rows] = value
        self.mean[rows], self.std[rows], self.task[rows] = mean, std, task
        if critic_value is not None:
            if self.value is None:
                self.value = _zeros(critic_value, (self.capacity,), np.float32)
            self.value[rows] = critic_value
        self._next = int((self._next + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def save(self, path: str | Path) -> None:
        """Write the stored states, their labels and the ring position to ``path`` (``.npz``)."""
        arrays = {f"obs/{key}": to_numpy(value[: self.size]) for key, value in self.obs.items()}
        if self.size:
            arrays.update({name: to_numpy(getattr(self, name)[: self.size]) for name in self._label_arrays()})
        meta = np.array([self.capacity, self.size, self._next], dtype=np.int64)
        with open(path, "wb") as f:  # a file object: np.savez would append .npz to a bare name
            np.savez(f, meta=meta, **arrays)

    @classmethod
    def load(cls, path: str | Path, capacity: int | None = None) -> DistillationDataset:
        """The dataset :meth:`save` wrote to ``path``.

        :param capacity: the capacity the caller expects; a file of another capacity is an error
            (its ring position would not mean the same rows). ``None``: the saved one.
        """
        with np.load(path) as saved:
            saved_capacity, size, next_row = (int(v) for v in saved["meta"])
            if capacity is not None and saved_capacity != capacity:
                raise ValueError(f"{path} holds a dataset of capacity {saved_capacity}, expected {capacity}")
            dataset = cls(saved_capacity)
            capacity = saved_capacity
            for name in saved.files:
                if name == "meta":
                    continue
                value = saved[name]
                if size < capacity:  # the rows not yet written stay zero, as in a fresh dataset
                    value = np.concatenate([value, np.zeros((capacity - size, *value.shape[1:]), dtype=value.dtype)])
                if name.startswith("obs/"):  # a full dataset takes the loaded arrays as they are: no second copy
                    dataset.obs[name.split("/", 1)[1]] = value
                else:
                    setattr(dataset, name, value)
        dataset.size, dataset._next = size, next_row
        return dataset

    def _label_arrays(self) -> tuple[str, ...]:
        """The per-state arrays besides the observations (subclasses add theirs)."""
        return ("mean", "std", "task") + (("value",) if self.value is not None else ())

    def to(self, device: th.device) -> DistillationDataset:
        """The storage as torch tensors on ``device`` (a resumed device distillation's dataset)."""
        self.obs = {k: th.as_tensor(v, device=device) for k, v in self.obs.items()}
        for name in self._label_arrays():
            if getattr(self, name) is not None:
                setattr(self, name, th.as_tensor(getattr(self, name), device=device))
        return self

    def batches(self, batch_size: int, rng: np.random.Generator, with_values: bool = False):
        """Shuffled minibatches over the stored states: ``(obs, mean, std, task)`` (``+ value`` with
        ``with_values``; tensors on the storage's device when it is torch; the shuffle is the same
        numpy permutation either way)."""
        order: Any = rng.permutation(self.size)
        if isinstance(self.task, th.Tensor):
            order = th.as_tensor(order, device=self.task.device)  # one copy per epoch, not per step
        for start in range(0, self.size, batch_size):
            rows = order[start : start + batch_size]
            if with_values:
                yield index_obs(self.obs, rows), self.mean[rows], self.std[rows], self.task[rows], self.value[rows]
            else:
                yield index_obs(self.obs, rows), self.mean[rows], self.std[rows], self.task[rows]
