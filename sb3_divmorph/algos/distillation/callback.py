"""The DAgger callback: label each rollout's states with their tasks' teachers, aggregate, fit the student."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize, unwrap_vec_wrapper

from sb3_divmorph.algos.device_ppo import DevicePPO
from sb3_divmorph.algos.distillation.dataset import DistillationDataset
from sb3_divmorph.algos.distillation.imitation_ppo import ImitationPPO
from sb3_divmorph.algos.distillation.labels import teacher_labels, teacher_labels_on_device, teacher_values
from sb3_divmorph.algos.distillation.losses import gaussian_kl
from sb3_divmorph.algos.distillation.mixing import TeacherMixingVecEnv
from sb3_divmorph.algos.distillation.observations import TASK_INDEX, ObsDict, to_numpy
from sb3_divmorph.algos.distillation.space_checks import SpaceMismatchError, check_spaces
from sb3_divmorph.algos.distillation.teacher import Teacher
from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, TASK_EMBEDDING
from sb3_divmorph.nn.gates import load_balancing_loss

#: Files of a :class:`DAggerCallback`'s state in a checkpoint folder.
DATASET_FILE = "dagger_dataset.npz"
STATE_FILE = "dagger_state.pt"


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
        self._normalizer = unwrap_vec_wrapper(self.training_env, VecNormalize)
        self._mixer = unwrap_vec_wrapper(self.training_env, TeacherMixingVecEnv)
        self._on_device = isinstance(self.model, DevicePPO) and self.model.device_mode
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
        # SB3's BaseAlgorithm keeps its last observation protected, with no public view
        source = fresh if fresh is not None else self.model._last_obs
        return {key: np.array(value, copy=True) for key, value in source.items()}

    def _on_rollout_start(self) -> None:
        # the progress SB3's schedules read: protected in BaseAlgorithm, with no public view
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
            normalizer = self.model.device_normalizer  # type: ignore[attr-defined]
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
                    task_rows = to_numpy(tasks)
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
