"""DAgger-style policy distillation: per-task teachers label the states a student visits.

DivMorph trains its knowledge-diverted student by distillation from one MetaMorph teacher per
training task. The pieces, usable with any SB3 on-policy algorithm:

* :class:`Teacher`: a trained policy with the observation normalisation it was trained under.
* :class:`DAggerCallback`: records the raw observations of every rollout, has each state labelled
  by the teacher of its own task (``task_index`` observation), aggregates them in a bounded
  dataset, and fits the student to the teachers' action distributions after each rollout.
* :class:`TeacherMixingVecEnv`: executes the teacher's action instead of the student's with
  probability ``beta`` (DAgger's beta-mixture), annealed by the callback.
* :class:`ImitationPPO`: PPO with its own update switched off, for pure distillation; with plain
  :class:`~stable_baselines3.PPO` the callback runs alongside the PPO loss.

**Loss.** For each state, ``KL(pi_teacher || pi_student)`` between the two diagonal Gaussians,
summed over the robot's real action slots (padded slots carry no action) and averaged over the
batch. With MetaMorph's fixed, equal standard deviations this is the squared error of the means
divided by ``2 sigma^2``; with a learnt student std it also matches the teacher's spread.

**On the device.** With :class:`ImitationPPO` (a :class:`~sb3_divmorph.algos.device_ppo.DevicePPO`)
on the batched MuJoCo Warp env, nothing of DAgger leaves the device in the rollout loop: the raw
states are the env's tensors (``DevicePPO.last_raw_obs``), every teacher labels them with its
statistics applied in torch (:func:`teacher_labels_on_device`), the aggregated dataset is stored as
tensors, and beta's teacher actions are mixed in by DevicePPO (``executed_actions``) instead of a
:class:`TeacherMixingVecEnv` (which would send every step through the host). The result is the
VecEnv path's: the same states, labels, dataset and update (``tests/test_device_ppo.py``).
"""

from __future__ import annotations

import pickle
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecNormalize
from torch.distributions import Normal, kl_divergence

from sb3_divmorph.algos.device_ppo import DeviceNormalizer, DevicePPO
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, TASK_EMBEDDING
from sb3_divmorph.nn.gates import load_balancing_loss

#: Observation key holding the index of the episode's task in ``unimal_envs.contract.TASK_NAMES``.
TASK_INDEX = "task_index"
#: Files of a :class:`DAggerCallback`'s state in a checkpoint folder.
DATASET_FILE = "dagger_dataset.npz"
STATE_FILE = "dagger_state.pt"

ObsDict = dict[str, np.ndarray]


class SpaceMismatchError(ValueError):
    """A saved model or normaliser does not fit the observation/action space it is used with."""


def check_spaces(what: str, saved: spaces.Space, expected: spaces.Space, kind: str = "observation") -> None:
    """Raise :class:`SpaceMismatchError` naming ``what`` and the differing keys if the spaces differ."""
    if saved == expected:
        return
    detail = ""
    if isinstance(saved, spaces.Dict) and isinstance(expected, spaces.Dict):
        differing = sorted(
            key
            for key in set(saved.spaces) | set(expected.spaces)
            if key not in saved.spaces or key not in expected.spaces or saved[key] != expected[key]
        )
        shapes = {k: (getattr(saved.spaces.get(k), "shape", None), getattr(expected.spaces.get(k), "shape", None)) for k in differing}
        detail = f"; differing keys (saved shape, env shape): {shapes}"
    else:
        detail = f"; saved {saved}, env {expected}"
    raise SpaceMismatchError(f"{what} was trained on a different {kind} space than this environment's{detail}")


def find_vec_wrapper(venv: VecEnv, wrapper: type) -> Any | None:
    """The first ``wrapper`` instance in a VecEnv wrapper stack, or ``None``."""
    while venv is not None:
        if isinstance(venv, wrapper):
            return venv
        venv = getattr(venv, "venv", None)
    return None


def load_normalizer(path: str | Path) -> VecNormalize:
    """Unpickle saved ``VecNormalize`` statistics without attaching an env (only ``normalize_obs`` is used)."""
    with open(path, "rb") as f:
        normalizer = pickle.load(f)
    if not isinstance(normalizer, VecNormalize):
        raise SpaceMismatchError(f"{path} does not hold VecNormalize statistics (found {type(normalizer).__name__})")
    normalizer.training = False
    return normalizer


def _zeros(like: Any, shape: tuple[int, ...], dtype: Any = None) -> Any:
    """Zeros of ``shape``: a tensor on ``like``'s device when ``like`` is a tensor, else numpy."""
    if isinstance(like, th.Tensor):
        torch_dtype = {np.float32: th.float32, np.int64: th.int64}.get(dtype, like.dtype)
        return th.zeros(shape, dtype=torch_dtype, device=like.device)
    return np.zeros(shape, dtype=dtype or like.dtype)


def _numpy(value: Any) -> np.ndarray:
    return value.cpu().numpy() if isinstance(value, th.Tensor) else value


def index_obs(obs: ObsDict, index: np.ndarray | slice) -> ObsDict:
    """Rows ``index`` of every key of a batched observation dict."""
    return {key: value[index] for key, value in obs.items()}


@dataclass
class Teacher:
    """A trained policy and the observation normalisation it saw during training.

    :param policy: the teacher's policy (eval mode, no gradients are taken through it).
    :param normalizer: its ``VecNormalize`` statistics, or ``None`` if it was trained on raw observations.
    :param name: label used in logs (usually the task name).
    """

    policy: ActorCriticPolicy
    normalizer: VecNormalize | None = None
    name: str = "teacher"
    _device_normalizer: Any = field(default=None, repr=False, compare=False)

    @classmethod
    def load(
        cls,
        model_path: str | Path,
        normalizer_path: str | Path | None = None,
        name: str | None = None,
        observation_space: spaces.Space | None = None,
        device: str | th.device = "cpu",
    ) -> Teacher:
        """Load a teacher saved with ``model.save`` (+ ``VecNormalize.save``).

        :param model_path: the ``.zip`` of a PPO model.
        :param normalizer_path: its VecNormalize ``.pkl`` (``None``: raw observations).
        :param name: label (default: the file's parent folder name).
        :param observation_space: if given, the teacher's space must equal it
            (:class:`SpaceMismatchError` otherwise).
        :param device: torch device of the teacher.
        """
        model_path = Path(model_path)
        if not model_path.is_file():
            raise FileNotFoundError(f"teacher checkpoint {model_path} does not exist")
        policy = PPO.load(model_path, device=device).policy
        policy.set_training_mode(False)
        if observation_space is not None:
            check_spaces(f"teacher {model_path}", policy.observation_space, observation_space)
        normalizer = load_normalizer(normalizer_path) if normalizer_path is not None else None
        if normalizer is not None and observation_space is not None:
            check_spaces(f"normalisation statistics {normalizer_path}", normalizer.observation_space, observation_space)
        return cls(policy, normalizer, name or model_path.parent.name)

    def normalize(self, raw_obs: ObsDict) -> ObsDict:
        return raw_obs if self.normalizer is None else self.normalizer.normalize_obs(raw_obs)

    def normalize_tensors(self, raw_obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """:meth:`normalize` on device tensors (``VecNormalize``'s arithmetic in torch, no host copy)."""
        if self.normalizer is None:
            return dict(raw_obs)
        device = next(iter(raw_obs.values())).device
        if self._device_normalizer is None or self._device_normalizer.device != device:
            self._device_normalizer = DeviceNormalizer(self.normalizer, device)
        return self._device_normalizer.normalize_obs(raw_obs)

    @th.no_grad()
    def action_distribution(self, raw_obs: ObsDict | Mapping[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """Mean and standard deviation (B, A) of the teacher's Gaussian on raw observations (numpy
        arrays, or tensors on the teacher's device: then nothing leaves the device)."""
        if all(isinstance(v, th.Tensor) for v in raw_obs.values()):
            obs = self.normalize_tensors(raw_obs)  # type: ignore[arg-type]
        else:
            obs, _ = self.policy.obs_to_tensor(self.normalize(raw_obs))  # type: ignore[arg-type]
        normal = self.policy.get_distribution(obs).distribution
        return normal.mean, normal.stddev.expand_as(normal.mean)

    @th.no_grad()
    def value(self, raw_obs: ObsDict | Mapping[str, th.Tensor]) -> th.Tensor:
        """The teacher critic's value (B,) of raw observations (numpy, or tensors on its device)."""
        if all(isinstance(v, th.Tensor) for v in raw_obs.values()):
            obs = self.normalize_tensors(raw_obs)  # type: ignore[arg-type]
        else:
            obs, _ = self.policy.obs_to_tensor(self.normalize(raw_obs))  # type: ignore[arg-type]
        return self.policy.predict_values(obs).flatten()

    def act(self, raw_obs: ObsDict) -> np.ndarray:
        """Deterministic (mean) actions, clipped to the action space."""
        mean, _ = self.action_distribution(raw_obs)
        space = self.policy.action_space
        return np.clip(mean.cpu().numpy(), space.low, space.high)


def _task_indices(raw_obs: ObsDict) -> np.ndarray:
    if TASK_INDEX not in raw_obs:
        raise KeyError(f"distillation needs the {TASK_INDEX!r} observation to pick each state's teacher")
    return np.rint(raw_obs[TASK_INDEX].reshape(len(raw_obs[TASK_INDEX]), -1)[:, 0]).astype(np.int64)


def _teacher_for(teachers: Mapping[int, Teacher], task_index: int) -> Teacher:
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
    tasks = _task_indices(raw_obs)
    mean = np.zeros((len(tasks), action_dim), dtype=np.float32)
    std = np.ones((len(tasks), action_dim), dtype=np.float32)
    for task in np.unique(tasks):
        teacher = _teacher_for(teachers, int(task))
        rows = np.flatnonzero(tasks == task)
        for start in range(0, len(rows), chunk):
            part = rows[start : start + chunk]
            m, s = teacher.action_distribution(index_obs(raw_obs, part))
            mean[part], std[part] = m.cpu().numpy(), s.cpu().numpy()
    return mean, std, tasks


class TeacherMixingVecEnv(VecEnvWrapper):
    """Executes each state's teacher action instead of the agent's with probability ``beta``.

    Place it below ``VecNormalize`` so it sees raw observations. ``beta = 0`` passes actions
    through untouched. The policy's rollout buffer still records the agent's own actions, so mix
    only in pure distillation (the PPO loss would be off-policy).

    :param venv: the vectorised env (observations must carry ``task_index``).
    :param teachers: ``{task index: teacher}``.
    :param beta: initial mixing probability.
    :param seed: seed of the mixing draws.
    """

    def __init__(self, venv: VecEnv, teachers: Mapping[int, Teacher], beta: float = 0.0, seed: int | None = None):
        super().__init__(venv)
        self.teachers = dict(teachers)
        self.beta = beta
        self.rng = np.random.default_rng(seed)
        self._obs: ObsDict | None = None
        self.teacher_steps = 0

    def reset(self):
        self._obs = self.venv.reset()
        return self._obs

    def step_async(self, actions: np.ndarray) -> None:
        if self.beta > 0 and self._obs is not None:
            chosen = np.flatnonzero(self.rng.random(self.num_envs) < self.beta)
            if len(chosen):
                actions = np.array(actions, copy=True)
                tasks = _task_indices(self._obs)
                for task in np.unique(tasks[chosen]):
                    rows = chosen[tasks[chosen] == task]
                    actions[rows] = _teacher_for(self.teachers, int(task)).act(index_obs(self._obs, rows))
                self.teacher_steps += len(chosen)
        self.venv.step_async(actions)

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        self._obs = obs
        return obs, rewards, dones, infos


def gaussian_kl(
    teacher_mean: th.Tensor, teacher_std: th.Tensor, student_mean: th.Tensor, student_std: th.Tensor, real: th.Tensor
) -> th.Tensor:
    """``KL(N_teacher || N_student)`` per sample, summed over real action slots: (B, A) x4, (B, A) bool -> (B,)."""
    per_slot = kl_divergence(Normal(teacher_mean, teacher_std), Normal(student_mean, student_std))
    return th.where(real, per_slot, th.zeros((), dtype=per_slot.dtype, device=per_slot.device)).sum(-1)


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
        arrays = {f"obs/{key}": _numpy(value[: self.size]) for key, value in self.obs.items()}
        if self.size:
            arrays.update({name: _numpy(getattr(self, name)[: self.size]) for name in self._label_arrays()})
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


class DAggerCallback(BaseCallback):
    """DAgger-style distillation of per-task teachers into the model being trained.

    After every rollout the callback labels the rollout's states with the teacher of each state's
    own task (each teacher sees the observations normalised with its own statistics), adds them to
    a bounded aggregated dataset, and takes ``epochs`` passes of minibatch gradient steps on the
    KL loss (module docstring) with its own Adam optimiser. The student sees the same raw states
    normalised by its own ``VecNormalize`` (if any). Use it with :class:`ImitationPPO` for pure
    distillation, or with ``PPO`` to add distillation to the PPO loss.

    Logged (TensorBoard/CSV through the model's logger): ``distill/loss``,
    ``distill/kl/<task>`` and ``distill/mean_abs_error/<task>`` (imitation error per task),
    ``distill/beta``, ``distill/dataset_size``, and for gated students ``gates/<kind>_entropy``,
    ``gates/<kind>_used`` (tailors with a non-zero gate in the batch: a falling count is gate
    collapse, a few tailors serving every robot or task), ``gates/<kind>_used_fraction``,
    ``gates/<kind>_usage`` (histogram of mean gate weight per tailor), and with ``load_balance``
    ``distill/load_balance_loss``. :attr:`tailor_usage` keeps the history of the used counts.

    Checkpoints: :meth:`save_state` / :meth:`load_state` keep the aggregated dataset, the optimiser
    and the shuffling generator (the pipeline's resumable runs call them), so that a resumed
    distillation continues the one it resumes.

    :param teachers: ``{task index: teacher}`` (index in ``unimal_envs.contract.TASK_NAMES``).
    :param task_names: names for logging, indexed like ``task_index``.
    :param beta: probability of executing the teacher's action; a float, or a function of the
        remaining progress (1 -> 0, as SB3 schedules). Needs a :class:`TeacherMixingVecEnv` in
        the env stack when it is ever non-zero.
    :param learning_rate: Adam learning rate of the distillation steps.
    :param epochs: passes over the aggregated dataset after each rollout.
    :param batch_size: minibatch size.
    :param buffer_size: capacity of the aggregated dataset (states).
    :param max_grad_norm: gradient clipping.
    :param seed: seed of the minibatch shuffling.
    :param load_balance: weight of a Switch-Transformer load-balancing term on both gates
        (:func:`~sb3_divmorph.nn.gates.load_balancing_loss`, minus its uniform value 1 per gate) added
        to the KL. Default 0 (off, DivMorph's recipe). Use it against gate collapse (a top-1 gate
        learns without it too: its weight is straight-through, see :class:`~sb3_divmorph.nn.gates.TopKSoftGate`).
    :param target_bound: clip the teachers' action means to ``[-bound, bound]`` before they become
        targets (``None``: as the teachers give them). The env clips actions at 1, so a teacher's
        mean of 5 and one of 1 act the same, but an unbounded target asks the student for the 5:
        bounded targets keep it no steeper than it must be.
    :param weight_decay: the optimiser's weight decay (with ``optimizer="adamw"``: decoupled, as
        DivControl trains its diverted model; with ``"adam"``: L2 added to the gradient).
    :param optimizer: ``"adam"`` (the default) or ``"adamw"``.
    :param value_weight: also regress the student's critic onto the state's teacher critic value
        (mean squared error, this weight; 0: the critic is not trained by distillation and starts
        transfer untrained).
    :param verbose: SB3 verbosity.
    """

    def __init__(
        self,
        teachers: Mapping[int, Teacher],
        task_names: tuple[str, ...] | list[str],
        beta: float | Callable[[float], float] = 0.0,
        learning_rate: float = 3e-4,
        epochs: int = 2,
        batch_size: int = 256,
        buffer_size: int = 50_000,
        max_grad_norm: float = 0.5,
        seed: int | None = None,
        load_balance: float = 0.0,
        target_bound: float | None = None,
        weight_decay: float = 0.0,
        optimizer: str = "adam",
        value_weight: float = 0.0,
        verbose: int = 0,
    ):
        super().__init__(verbose)
        if not teachers:
            raise ValueError("DAggerCallback needs at least one teacher")
        if load_balance < 0:
            raise ValueError(f"load_balance must be >= 0, got {load_balance}")
        if target_bound is not None and target_bound <= 0:
            raise ValueError(f"target_bound must be positive (or None: unbounded), got {target_bound}")
        if optimizer not in ("adam", "adamw"):
            raise ValueError(f"optimizer must be 'adam' or 'adamw', got {optimizer!r}")
        if weight_decay < 0 or value_weight < 0:
            raise ValueError(f"weight_decay and value_weight must be >= 0, got {weight_decay} and {value_weight}")
        self.target_bound = target_bound
        self.weight_decay = float(weight_decay)
        self.optimizer_name = optimizer
        self.value_weight = float(value_weight)
        self.load_balance = float(load_balance)
        #: ``{"morphology": [...], "task": [...]}``: tailors in use after each distillation round
        self.tailor_usage: dict[str, list[int]] = {"morphology": [], "task": []}
        self.teachers = dict(teachers)
        self.task_names = list(task_names)
        self.beta = beta if callable(beta) else (lambda _progress, value=float(beta): value)
        self.learning_rate = learning_rate
        self.epochs = epochs
        self.batch_size = batch_size
        self.dataset = DistillationDataset(buffer_size)
        self.max_grad_norm = max_grad_norm
        self.rng = np.random.default_rng(seed)
        self.optimizer: th.optim.Optimizer | None = None
        self._rollout_obs: list[ObsDict] = []
        self._normalizer: VecNormalize | None = None
        self._mixer: TeacherMixingVecEnv | None = None
        self._optimizer_state: dict[str, Any] | None = None  # restored by load_state, applied at training start
        #: on a DevicePPO in device mode: states, labels, dataset and mixing stay on the env's device
        self._on_device = False
        self._mix_seed = seed
        self._mix_generator: th.Generator | None = None
        self._beta_now = 0.0
        #: (device mode) states at which a teacher's action was executed, as a device tensor
        self.teacher_steps: Any = 0

    # -- checkpoints ---------------------------------------------------------------------------
    def save_state(self, folder: Path) -> None:
        """Save what a resumed distillation needs besides the model into ``folder``: the aggregated
        dataset (``dagger_dataset.npz``), the optimiser, the shuffling generator and the tailor
        usage history (``dagger_state.pt``)."""
        self.dataset.save(Path(folder) / DATASET_FILE)
        state = {
            "optimizer": self.optimizer.state_dict() if self.optimizer is not None else None,
            "rng": self.rng.bit_generator.state,
            "tailor_usage": self.tailor_usage,
        }
        th.save(state, Path(folder) / STATE_FILE)

    def load_state(self, folder: Path) -> None:
        """Restore what :meth:`save_state` wrote (the optimiser once training starts).

        A checkpoint without these files (written before they were saved) resumes with an empty
        dataset and a fresh optimiser, with a warning.
        """
        folder = Path(folder)
        missing = [name for name in (DATASET_FILE, STATE_FILE) if not (folder / name).is_file()]
        if missing:
            warnings.warn(
                f"checkpoint {folder} has no distillation state ({', '.join(missing)}): "
                "DAgger resumes with an empty aggregated dataset and a fresh optimiser",
                stacklevel=2,
            )
            return
        self.dataset = DistillationDataset.load(folder / DATASET_FILE, self.dataset.capacity)
        state = th.load(folder / STATE_FILE, weights_only=False)
        self._optimizer_state = state["optimizer"]
        self.rng.bit_generator.state = state["rng"]
        self.tailor_usage = state["tailor_usage"]

    # -- SB3 hooks -----------------------------------------------------------------------------
    def _init_callback(self) -> None:
        obs_space = self.model.observation_space
        if not isinstance(obs_space, spaces.Dict) or TASK_INDEX not in obs_space.spaces:
            raise SpaceMismatchError(f"distillation needs a Dict observation space with {TASK_INDEX!r}")
        for teacher in self.teachers.values():
            check_spaces(f"teacher {teacher.name}", teacher.policy.observation_space, obs_space)
            check_spaces(f"teacher {teacher.name}", teacher.policy.action_space, self.model.action_space, "action")
        self._normalizer = find_vec_wrapper(self.training_env, VecNormalize)
        self._mixer = find_vec_wrapper(self.training_env, TeacherMixingVecEnv)
        self._on_device = isinstance(self.model, DevicePPO) and self.model._device_chain() is not None
        if self._on_device:
            device = self.model.device
            away = [t.name for t in self.teachers.values() if t.policy.device != device]
            if away:
                raise ValueError(
                    f"device distillation: teachers {away} are not on the env's device {device}; load them with device={device}"
                )
            if self.dataset.size and not isinstance(self.dataset.task, th.Tensor):
                self.dataset.to(device)  # resumed from a checkpoint
            self._mix_generator = th.Generator(device=device)
            self._mix_generator.manual_seed(0 if self._mix_seed is None else int(self._mix_seed))
        optimizer_class = th.optim.AdamW if self.optimizer_name == "adamw" else th.optim.Adam
        self.optimizer = optimizer_class(self.model.policy.parameters(), lr=self.learning_rate, weight_decay=self.weight_decay)
        if self._optimizer_state is not None:
            self.optimizer.load_state_dict(self._optimizer_state)
            self._optimizer_state = None

    def _current_raw_obs(self, fresh: ObsDict | None = None) -> ObsDict:
        if self._on_device:  # the env's latest raw observation, kept by DevicePPO (copied: the env reuses its buffers)
            return {key: value.clone() for key, value in self.model.last_raw_obs.items()}  # type: ignore[return-value]
        if self._normalizer is not None:
            return self._normalizer.get_original_obs()
        source = fresh if fresh is not None else self.model._last_obs
        return {key: np.array(value, copy=True) for key, value in source.items()}

    def _on_rollout_start(self) -> None:
        beta = float(self.beta(self.model._current_progress_remaining))
        if beta > 0:
            if self._mixer is None and not self._on_device:
                raise ValueError("beta > 0 needs the training env wrapped in TeacherMixingVecEnv (below VecNormalize)")
            if not isinstance(self.model, ImitationPPO):
                raise ValueError("beta > 0 (teacher actions executed) is off-policy for PPO: use ImitationPPO")
        if self._mixer is not None:
            self._mixer.beta = beta
        if self._on_device:  # DevicePPO executes the mixed actions; its buffer keeps the student's
            self._beta_now = beta
            self.model.executed_actions = self._mix if beta > 0 else None  # type: ignore[attr-defined]
        self.logger.record("distill/beta", beta)
        self._rollout_obs = [self._current_raw_obs()]

    def _on_step(self) -> bool:
        self._rollout_obs.append(self._current_raw_obs(self.locals.get("new_obs")))
        return True

    def _on_rollout_end(self) -> None:
        # the last entry is the state after the final step: it belongs to the next rollout
        states = self._rollout_obs[:-1]
        self._rollout_obs = []
        if not states:
            return
        if self._on_device:
            obs = {key: th.cat([s[key] for s in states]) for key in states[0]}
            mean, std, tasks = teacher_labels_on_device(self.teachers, obs)
        else:
            obs = {key: np.concatenate([s[key] for s in states]) for key in states[0]}
            mean, std, tasks = self.label(obs)
        if self.target_bound is not None:
            mean = (
                mean.clamp(-self.target_bound, self.target_bound)
                if isinstance(mean, th.Tensor)
                else np.clip(mean, -self.target_bound, self.target_bound)
            )
        value = teacher_values(self.teachers, obs, tasks) if self.value_weight > 0 else None
        self.dataset.add(obs, mean, std, tasks, value)
        self.train()

    # -- distillation --------------------------------------------------------------------------
    def label(self, raw_obs: ObsDict, chunk: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Teacher means and stds for a batch of raw states, each by its own task's teacher."""
        return teacher_labels(self.teachers, raw_obs, int(np.prod(self.model.action_space.shape)), chunk)

    def _mix(self, raw_obs: Mapping[str, th.Tensor], actions: th.Tensor) -> th.Tensor:
        """(device mode) Each world's teacher action instead of ``actions`` with probability beta."""
        chosen = th.rand(actions.shape[0], device=actions.device, generator=self._mix_generator) < self._beta_now
        mean, _, _ = teacher_labels_on_device(self.teachers, raw_obs)
        space = self.model.action_space
        teacher_actions = mean.clamp(float(space.low.min()), float(space.high.max()))
        self.teacher_steps = self.teacher_steps + chosen.sum()
        return th.where(chosen.unsqueeze(-1), teacher_actions, actions)

    def _student_obs(self, raw_obs: ObsDict) -> ObsDict:
        if self._on_device:  # the model's device mirror of its VecNormalize, as of this rollout's end
            normalizer = self.model._device_state.get("normalizer")  # type: ignore[attr-defined]
            return raw_obs if normalizer is None else normalizer.normalize_obs(raw_obs)
        return raw_obs if self._normalizer is None else self._normalizer.normalize_obs(raw_obs)

    def train(self) -> None:
        """``epochs`` passes of KL minimisation over the aggregated dataset."""
        policy = self.model.policy
        policy.set_training_mode(True)
        device = policy.device
        losses: list[float] = []
        kl_sum = np.zeros(len(self.task_names))
        err_sum = np.zeros(len(self.task_names))
        count = np.zeros(len(self.task_names))
        gate_stats: list[Any] = []
        balance_sum = value_sum = 0.0
        for epoch in range(self.epochs):
            for batch in self.dataset.batches(self.batch_size, self.rng, with_values=self.value_weight > 0):
                raw, t_mean, t_std, tasks = batch[:4]
                if self._on_device:
                    obs = self._student_obs(raw)
                else:
                    obs, _ = policy.obs_to_tensor(self._student_obs(raw))
                student = policy.get_distribution(obs)
                real = obs[ACT_PADDING_MASK] < 0.5
                t_mean_t = th.as_tensor(t_mean, device=device)
                t_std_t = th.as_tensor(t_std, device=device)
                s_mean = student.distribution.mean
                kl = gaussian_kl(t_mean_t, t_std_t, s_mean, student.distribution.stddev.expand_as(s_mean), real)
                loss = kl.mean()
                if self.value_weight > 0:
                    value_error = (policy.predict_values(obs).flatten() - th.as_tensor(batch[4], device=device)).square().mean()
                    value_sum += value_error.item()
                    loss = loss + self.value_weight * value_error
                if self.load_balance > 0 and hasattr(policy, "router"):
                    balance = self._balance_loss(policy, obs)
                    balance_sum = balance_sum + balance.item()
                    loss = loss + self.load_balance * balance
                self.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(policy.parameters(), self.max_grad_norm)
                self.optimizer.step()
                losses.append(loss.item())
                if epoch == self.epochs - 1:
                    with th.no_grad():
                        abs_err = th.where(real, (s_mean - t_mean_t).abs(), th.zeros((), device=device)).sum(-1)
                        abs_err = abs_err / real.sum(-1).clamp(min=1)
                    task_rows = _numpy(tasks)
                    np.add.at(kl_sum, task_rows, kl.detach().cpu().numpy())
                    np.add.at(err_sum, task_rows, abs_err.cpu().numpy())
                    np.add.at(count, task_rows, 1)
                    if hasattr(policy, "get_gates") and len(gate_stats) < 4:
                        gate_stats.append(policy.get_gates(obs))
        policy.set_training_mode(False)
        self.logger.record("distill/loss", float(np.mean(losses)))
        if self.load_balance > 0:
            self.logger.record("distill/load_balance_loss", balance_sum / max(len(losses), 1))
        if self.value_weight > 0:
            self.logger.record("distill/value_error", value_sum / max(len(losses), 1))
        self.logger.record("distill/dataset_size", self.dataset.size)
        for index in np.flatnonzero(count):
            name = self.task_names[index]
            self.logger.record(f"distill/kl/{name}", kl_sum[index] / count[index])
            self.logger.record(f"distill/mean_abs_error/{name}", err_sum[index] / count[index])
        if gate_stats:
            self._log_gates(gate_stats)

    @staticmethod
    def _balance_loss(policy: Any, obs: Mapping[str, th.Tensor]) -> th.Tensor:
        """Load balance of both gates, 0 when tailor use is uniform."""
        gates, probabilities = policy.router.route_with_probabilities(
            obs[CONTEXT], obs[OBS_PADDING_MASK] > 0.5, obs[TASK_EMBEDDING].flatten(1)
        )
        return sum(load_balancing_loss(w, p) - 1.0 for w, p in zip(gates, probabilities))

    def _log_gates(self, gate_stats: list[Any]) -> None:
        for kind in ("morphology", "task"):
            gates = th.cat([getattr(g, kind) for g in gate_stats])
            positive = gates.clamp(min=1e-12)
            entropy = -(gates * positive.log()).sum(-1).mean()
            usage = gates.mean(0)
            used = int((gates > 0).any(0).sum())
            self.tailor_usage[kind].append(used)
            self.logger.record(f"gates/{kind}_entropy", entropy.item())
            self.logger.record(f"gates/{kind}_used", used)
            self.logger.record(f"gates/{kind}_used_fraction", used / gates.shape[-1])
            self.logger.record(f"gates/{kind}_usage", usage.cpu(), exclude=("stdout", "log", "json", "csv"))


class ImitationPPO(DevicePPO):
    """PPO that collects rollouts but skips its own policy-gradient update (on the batched env's
    device when it is one: :class:`~sb3_divmorph.algos.device_ppo.DevicePPO`).

    For pure distillation: a :class:`DAggerCallback` does all the learning from the rollouts this
    algorithm collects (with the student's actions, or the teachers' under a
    :class:`TeacherMixingVecEnv`). Everything else (rollouts, logging, saving, ``learn``'s progress
    bar) is PPO's.
    """

    def train(self) -> None:
        self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
