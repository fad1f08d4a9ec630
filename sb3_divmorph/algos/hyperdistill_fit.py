"""Training a HyperDistill student offline: teacher rollouts, the NLL / KL losses, and the fit.

Offline distillation (the authors' recipe): roll out the teachers (:func:`collect_teacher_rollouts`,
each state acted on by its own task's teacher, sampling from its Gaussian), then fit the student
to those states (:func:`fit_offline`; loss = NLL of the teacher's sampled action, the authors'
default, or the KL of :func:`~sb3_divmorph.algos.distillation.gaussian_kl`). :func:`load_student`
reads a saved student back, checking its observation space.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecNormalize, unwrap_vec_wrapper
from torch import nn

from sb3_divmorph.algos.distillation import (
    DistillationDataset,
    ObsDict,
    Teacher,
    check_spaces,
    gaussian_kl,
    teacher_labels,
)
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK
from sb3_divmorph.policies.hyperdistill import LOSSES, HyperDistillPolicy


def load_student(path: str | Path, observation_space: spaces.Space | None = None, device: str = "cpu") -> HyperDistillPolicy:
    """A saved HyperDistill student (``model.zip``); its observation space must equal ``observation_space``.

    :raises SpaceMismatchError: the checkpoint was trained on another observation space.
    :raises TypeError: the checkpoint holds another policy.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"HyperDistill checkpoint {path} does not exist")
    policy = PPO.load(path, device=device).policy
    if not isinstance(policy, HyperDistillPolicy):
        raise TypeError(f"{path} holds a {type(policy).__name__}, not a HyperDistill student")
    if observation_space is not None:
        check_spaces(f"HyperDistill checkpoint {path}", policy.observation_space, observation_space)
    return policy.eval()


# -- offline distillation from teacher rollouts ------------------------------------------------------
class TeacherRollouts(DistillationDataset):
    """Teacher-labelled states of teacher rollouts, with the teacher's *sampled* action (for the NLL loss)."""

    def __init__(self, capacity: int):
        super().__init__(capacity)
        self.actions: np.ndarray | None = None

    def add_with_actions(self, obs: ObsDict, mean: np.ndarray, std: np.ndarray, task: np.ndarray, actions: np.ndarray) -> None:
        if self.actions is None:
            self.actions = np.zeros((self.capacity, actions.shape[1]), dtype=np.float32)
        rows = (self._next + np.arange(len(task))) % self.capacity
        self.actions[rows] = actions
        self.add(obs, mean, std, task)

    def _label_arrays(self) -> tuple[str, ...]:
        return (*super()._label_arrays(), "actions")

    def batches_with_actions(self, batch_size: int, rng: np.random.Generator):
        """Shuffled minibatches ``(obs, mean, std, task, action)``."""
        order = rng.permutation(self.size)
        for start in range(0, self.size, batch_size):
            rows = order[start : start + batch_size]
            yield {k: v[rows] for k, v in self.obs.items()}, self.mean[rows], self.std[rows], self.task[rows], self.actions[rows]


def collect_teacher_rollouts(
    teachers: Mapping[int, Teacher], venv: VecEnv, n_samples: int, seed: int = 0, capacity: int | None = None, verbose: int = 0
) -> TeacherRollouts:
    """Roll out the teachers (each state acted on by its own task's teacher, sampling from its Gaussian).

    :param teachers: ``{task index: teacher}``.
    :param venv: the student's env stack, observations with ``task_index``; a ``VecNormalize`` in it
        keeps updating its statistics (the student's normalisation), raw states are stored.
    :param n_samples: states to collect (rounded up to whole vector steps).
    :param seed: seed of the action noise.
    :param capacity: dataset capacity (default ``n_samples`` rounded up).
    :param verbose: 1: a line at every tenth of the states collected (count, rate).
    """
    rng = np.random.default_rng(seed)
    normalizer = unwrap_vec_wrapper(venv, VecNormalize)
    steps = math.ceil(n_samples / venv.num_envs)
    dataset = TeacherRollouts(capacity or steps * venv.num_envs)
    obs = venv.reset()
    low, high = venv.action_space.low, venv.action_space.high
    action_dim = int(np.prod(venv.action_space.shape))
    start, report_every = time.perf_counter(), max(1, steps // 10)
    for step in range(steps):
        raw = normalizer.get_original_obs() if normalizer is not None else {k: np.array(v) for k, v in obs.items()}
        mean, std, tasks = teacher_labels(teachers, raw, action_dim)
        actions = (mean + std * rng.standard_normal(mean.shape)).astype(np.float32)
        dataset.add_with_actions(raw, mean, std, tasks, actions)
        obs, _, _, _ = venv.step(np.clip(actions, low, high))
        if verbose and ((step + 1) % report_every == 0 or step + 1 == steps):
            elapsed = time.perf_counter() - start
            print(
                f"[hyperdistill] teacher rollouts: {dataset.size} of {steps * venv.num_envs} states ({dataset.size / elapsed:.0f} states/s)"
            )
    return dataset


def gaussian_nll(mean: th.Tensor, std: th.Tensor, actions: th.Tensor, real: th.Tensor) -> th.Tensor:
    """Negative log-likelihood of ``actions`` under ``N(mean, std)``, summed over real slots: (B,)."""
    per_slot = -th.distributions.Normal(mean, std).log_prob(actions)
    return th.where(real, per_slot, th.zeros((), dtype=per_slot.dtype, device=per_slot.device)).sum(-1)


def distillation_loss(
    policy: HyperDistillPolicy, obs: Mapping[str, th.Tensor], t_mean: th.Tensor, t_std: th.Tensor, t_action: th.Tensor | None, loss: str
) -> th.Tensor:
    """Mean over the batch of the NLL of the teacher's action (``"nll"``) or ``KL(teacher || student)`` (``"kl"``)."""
    if loss not in LOSSES:
        raise ValueError(f"unknown distillation loss {loss!r}; choose from {list(LOSSES)}")
    student = policy.get_distribution(obs).distribution
    real = obs[ACT_PADDING_MASK] < 0.5
    s_std = student.stddev.expand_as(student.mean)
    if loss == "nll":
        return gaussian_nll(student.mean, s_std, t_action, real).mean()
    return gaussian_kl(t_mean, t_std, student.mean, s_std, real).mean()


def fit_offline(
    policy: HyperDistillPolicy,
    dataset: TeacherRollouts,
    normalizer: VecNormalize | None = None,
    loss: str = "nll",
    epochs: int = 10,
    batch_size: int = 5120,
    learning_rate: float = 3e-4,
    max_grad_norm: float | None = None,
    seed: int = 0,
    checkpoint: str | Path | None = None,
    verbose: int = 0,
) -> list[float]:
    """Fit the student to teacher rollouts by minibatch Adam; returns the mean loss of every epoch.

    :param policy: the student.
    :param dataset: from :func:`collect_teacher_rollouts`.
    :param normalizer: the student's observation normalisation (applied to the stored raw states).
    :param loss: ``"nll"`` (authors' default) or ``"kl"``.
    :param epochs: passes over the dataset.
    :param batch_size: minibatch size (authors: 5120).
    :param learning_rate: Adam learning rate (authors: 1e-3 / 3e-4 / 1e-4).
    :param max_grad_norm: gradient clipping (``None``: none).
    :param seed: shuffling seed.
    :param checkpoint: a file written (atomically) after every epoch with the student, the optimiser,
        the shuffling state and the losses so far; when it exists the fit resumes from it and ends
        as an uninterrupted fit would have. The caller removes it once the student is saved.
    :param verbose: 1: a line per epoch (mean loss, seconds).
    """
    if loss not in LOSSES:
        raise ValueError(f"unknown distillation loss {loss!r}; choose from {list(LOSSES)}")
    optimizer = th.optim.Adam(policy.parameters(), lr=learning_rate)
    rng = np.random.default_rng(seed)
    device = policy.device
    history: list[float] = []
    if checkpoint is not None and Path(checkpoint).is_file():
        state = th.load(checkpoint, map_location=device, weights_only=False)
        policy.load_state_dict(state["policy"])
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        history = list(state["history"])
        if verbose:
            print(f"[hyperdistill] offline fit: resuming after epoch {len(history)} of {epochs} ({checkpoint})")
    policy.set_training_mode(True)
    for epoch in range(len(history), epochs):
        start, losses = time.perf_counter(), []
        for raw, t_mean, t_std, _, t_action in dataset.batches_with_actions(batch_size, rng):
            obs, _ = policy.obs_to_tensor(raw if normalizer is None else normalizer.normalize_obs(raw))
            value = distillation_loss(
                policy,
                obs,
                th.as_tensor(t_mean, device=device),
                th.as_tensor(t_std, device=device),
                th.as_tensor(t_action, device=device),
                loss,
            )
            optimizer.zero_grad()
            value.backward()
            if max_grad_norm is not None:
                th.nn.utils.clip_grad_norm_(policy.parameters(), max_grad_norm)
            optimizer.step()
            losses.append(value.item())
        history.append(float(np.mean(losses)))
        if checkpoint is not None:
            _save_fit_state(Path(checkpoint), policy, optimizer, rng, history)
        if verbose:
            print(
                f"[hyperdistill] offline fit: epoch {epoch + 1} of {epochs}, {loss} {history[-1]:.4g} ({time.perf_counter() - start:.0f} s)"
            )
    policy.set_training_mode(False)
    return history


def _save_fit_state(path: Path, policy: nn.Module, optimizer: th.optim.Optimizer, rng: np.random.Generator, history: list[float]) -> None:
    """Write the offline fit's state next to ``path`` and rename it over ``path`` (a kill leaves the old one)."""
    staging = path.with_name(f".staging-{path.name}")
    th.save(
        {"policy": policy.state_dict(), "optimizer": optimizer.state_dict(), "rng": rng.bit_generator.state, "history": history}, staging
    )
    os.replace(staging, path)
