"""PPO whose rollouts never leave the device: :class:`DevicePPO` on the batched env's tensors.

SB3's PPO talks to its env through the ``VecEnv`` interface: every step it copies each world's
observation to numpy (~8 KB a world), builds one Python ``info`` dict per world, copies the
observations back to the policy's device, the actions to numpy and back, and the values and
log-probabilities to numpy for its rollout buffer. :class:`DevicePPO` is SB3's PPO with one
difference: when its env is a :class:`~unimal_envs.batched.BatchedUnimalEnv` (optionally wrapped
in ``VecMonitor`` and/or ``VecNormalize``, as the pipeline builds it), rollouts are collected
through the env's torch interface (:meth:`~unimal_envs.batched.BatchedUnimalEnv.step_tensors`):

* observations, actions, rewards, dones, values and log-probabilities stay on the env's device,
  in a rollout buffer of torch tensors (:class:`DeviceDictRolloutBuffer`); GAE runs there too;
* ``VecNormalize``'s arithmetic runs in torch on the device (:class:`DeviceNormalizer`: running
  mean/var per key, the same keys, clip, epsilon, discounted-return reward scaling) on the
  statistics of the very ``VecNormalize`` object in the env chain: they are read from it at the
  start of every rollout and written back at its end, so ``model.get_vec_normalize_env().save()``,
  ``VecNormalize.load`` and the pipeline's checkpoints work unchanged;
* episode returns and lengths (``VecMonitor``'s ``rollout/ep_rew_mean`` and ``ep_len_mean``) are
  kept in tensors and handed to SB3's ``ep_info_buffer`` once per rollout;
* a world truncated by the time limit is bootstrapped with the value of its final observation,
  as SB3 does (``reward += gamma * V(terminal observation)``);
* the update is SB3's own ``PPO.train()``; the buffer's ``get()`` yields
  ``DictRolloutBufferSamples`` of device tensors.

Per control step the hot loop crosses from device to host only for two scalars (the env's
"did any world end" check that guards its auto-reset, and "was any world truncated" that guards
the bootstrap), and never builds a per-world Python object; per rollout it copies the finished
episodes' returns and lengths and the normaliser's statistics (a few KB). With any other env,
:class:`DevicePPO` is exactly SB3's PPO.

The cost of the ``VecEnv`` path it replaces (what ``PPO`` on a ``BatchedUnimalEnv`` pays per
step) is what ``benchmarks/batched_throughput.py`` measures.

Callbacks still run every step; in device mode their ``locals`` hold tensors: ``new_obs`` (a dict
of normalised observation tensors), ``rewards`` and ``dones`` (``(num_envs,)`` tensors) and
``infos`` (the env's dict of tensors from ``step_tensors``, not a list of per-world dicts).
``VecNormalize``'s statistics are written back at the end of each rollout, so a callback that
reads them mid-rollout (``EvalCallback``'s normalisation sync) sees them as of the last rollout.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Generator, Iterable, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common import utils
from stable_baselines3.common.buffers import DictRolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.type_aliases import DictRolloutBufferSamples
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecMonitor, VecNormalize

from sb3_divmorph.algos.vec_normalize import LeanVecNormalize
from torch.overrides import TorchFunctionMode

__all__ = ["DevicePPO", "DeviceDictRolloutBuffer", "DeviceNormalizer", "HostTransferCounter", "TorchRunningMeanStd", "device_env_chain"]


# ---------------------------------------------------------------------------- env chain
def _batched_env_class() -> type | None:
    """:class:`BatchedUnimalEnv`, or ``None`` when MuJoCo Warp is not installed."""
    from unimal_envs import batched

    if batched._MISSING is not None:
        return None
    from unimal_envs.batched.env import BatchedUnimalEnv

    return BatchedUnimalEnv


def _mirrored_statistics(rms: Any) -> bool:
    """Statistics whose update :class:`TorchRunningMeanStd` reproduces: SB3's own, or frozen ones
    (:class:`~sb3_divmorph.algos.finetune.FrozenRunningMeanStd`, never updated)."""
    from sb3_divmorph.algos.finetune import FrozenRunningMeanStd

    return type(rms) in (RunningMeanStd, FrozenRunningMeanStd)


def device_env_chain(env: VecEnv | None) -> tuple[Any, VecNormalize | None] | None:
    """``(batched env, VecNormalize or None)`` when ``env`` is a :class:`BatchedUnimalEnv` wrapped
    only in ``VecMonitor`` and/or one ``VecNormalize`` (exactly those classes or :class:`LeanVecNormalize`, whose
    arithmetic is SB3's, with SB3's or frozen
    statistics: the wrappers whose work :class:`DevicePPO` does on the device); ``None`` otherwise
    (any other env, wrapper or statistics class: SB3's own path, whose semantics are then kept).

    :param env: the algorithm's env (``model.env``).
    """
    if env is None:
        return None
    normalizer = None
    while isinstance(env, VecEnvWrapper):
        if type(env) in (VecNormalize, LeanVecNormalize) and normalizer is None:
            statistics = list(env.obs_rms.values()) if isinstance(getattr(env, "obs_rms", None), dict) else []
            if not all(_mirrored_statistics(rms) for rms in [*statistics, env.ret_rms]):
                return None
            normalizer = env
        elif type(env) is not VecMonitor:
            return None
        env = env.venv
    batched = _batched_env_class()
    if batched is None or not isinstance(env, batched):
        return None
    return env, normalizer


# ---------------------------------------------------------------------------- normalisation
class TorchRunningMeanStd:
    """SB3's :class:`~stable_baselines3.common.running_mean_std.RunningMeanStd` in torch (float64
    on the device): the same parallel-moments update, so the statistics match to rounding.

    :param mean: running mean.
    :param var: running (population) variance.
    :param count: samples seen (a Python float, as SB3 keeps it; starts at ``1e-4``).
    """

    def __init__(self, mean: th.Tensor, var: th.Tensor, count: float):
        self.mean, self.var, self.count = mean, var, float(count)

    @classmethod
    def from_numpy(cls, rms: RunningMeanStd, device: th.device) -> TorchRunningMeanStd:
        """A device copy of ``rms``."""
        as_tensor = lambda a: th.as_tensor(np.asarray(a, dtype=np.float64), device=device).clone()  # noqa: E731
        return cls(as_tensor(rms.mean), as_tensor(rms.var), float(rms.count))

    def write_to(self, rms: RunningMeanStd) -> None:
        """Copy the statistics back into ``rms`` (numpy float64, as SB3 stores them)."""
        rms.mean = self.mean.cpu().numpy().astype(np.float64)
        rms.var = self.var.cpu().numpy().astype(np.float64)
        rms.count = self.count

    def update(self, x: th.Tensor) -> None:
        """Fold in a batch ``x`` of shape ``(batch, *shape)``."""
        # the batch's moments in its own dtype, then float64: as numpy does in RunningMeanStd.update
        batch_mean, batch_var, batch_count = x.mean(0).double(), x.var(0, unbiased=False).double(), x.shape[0]
        delta = batch_mean - self.mean
        total = self.count + batch_count
        m2 = self.var * self.count + batch_var * batch_count + delta.square() * self.count * batch_count / total
        self.mean = self.mean + delta * batch_count / total
        self.var = m2 / total
        self.count = batch_count + self.count


class DeviceNormalizer:
    """``VecNormalize``'s arithmetic on the device, on the statistics of ``source``.

    Observations: per-key running mean/var (``source.norm_obs_keys``), ``clip((x - mean) /
    sqrt(var + epsilon), -clip_obs, clip_obs)``, updated with every batch of observations the env
    returns while ``source.training``. Rewards: the discounted return ``R = gamma * R + r`` feeds a
    running variance and ``clip(r / sqrt(var + epsilon), -clip_reward, clip_reward)``; ``R`` is
    zeroed where an episode ends. All as :class:`~stable_baselines3.common.vec_env.VecNormalize`.

    :param source: the ``VecNormalize`` whose statistics and settings are used (:meth:`pull`) and
        kept up to date (:meth:`push`).
    :param device: where the statistics live (the env's device).
    """

    def __init__(self, source: VecNormalize, device: th.device):
        self.source, self.device = source, device
        self.pull()

    def pull(self) -> None:
        """Read statistics and settings from ``source`` (its state may have changed between rollouts)."""
        s = self.source
        self.training, self.norm_obs, self.norm_reward = s.training, s.norm_obs, s.norm_reward
        self.clip_obs, self.clip_reward, self.gamma, self.epsilon = s.clip_obs, s.clip_reward, s.gamma, s.epsilon
        self.keys = list(s.norm_obs_keys or []) if self.norm_obs else []
        if self.norm_obs and not isinstance(s.obs_rms, dict):
            raise TypeError("DevicePPO normalises dict observations; this VecNormalize has a single obs_rms")
        self.obs_rms = {k: TorchRunningMeanStd.from_numpy(s.obs_rms[k], self.device) for k in self.keys}
        #: keys whose statistics are frozen (FrozenRunningMeanStd): used, never updated nor written back
        self.frozen = {k for k in self.keys if type(s.obs_rms[k]) is not RunningMeanStd}
        self.returns_frozen = type(s.ret_rms) is not RunningMeanStd
        self.ret_rms = TorchRunningMeanStd.from_numpy(s.ret_rms, self.device)
        # statistics unpickled without an env (a teacher's) have no running returns: only observations are normalised then
        returns = s.__dict__.get("returns")
        self.returns = th.as_tensor(np.asarray(0.0 if returns is None else returns, dtype=np.float64), device=self.device).clone()

    def push(self) -> None:
        """Write the statistics back into ``source`` (so saving it saves them)."""
        for key, rms in self.obs_rms.items():
            if key not in self.frozen:
                rms.write_to(self.source.obs_rms[key])
        if not self.returns_frozen:
            self.ret_rms.write_to(self.source.ret_rms)
        self.source.returns = self.returns.cpu().numpy()

    def normalize_obs(self, obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Normalised copy of ``obs`` (keys not normalised are passed through); no update."""
        out = dict(obs)
        for key in self.keys:
            rms = self.obs_rms[key]
            scaled = (obs[key].double() - rms.mean) / th.sqrt(rms.var + self.epsilon)
            out[key] = scaled.clamp(-self.clip_obs, self.clip_obs).float()
        return out

    def reset(self, obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """As ``VecNormalize.reset``: zero the returns, update with ``obs`` when training, normalise."""
        self.returns.zero_()
        return self.observe(obs)

    def observe(self, obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Update the observation statistics with ``obs`` (when training), then normalise it."""
        if self.training:
            for key in self.keys:
                if key not in self.frozen:
                    self.obs_rms[key].update(obs[key])
        return self.normalize_obs(obs)

    def reward(self, reward: th.Tensor, dones: th.Tensor) -> th.Tensor:
        """Update the return statistics with ``reward`` (when training) and scale it; then zero the
        returns of the worlds in ``dones``."""
        if self.training:
            self.returns = self.returns * self.gamma + reward.double()
            if not self.returns_frozen:
                self.ret_rms.update(self.returns)
        if self.norm_reward:
            reward = (reward.double() / th.sqrt(self.ret_rms.var + self.epsilon)).clamp(-self.clip_reward, self.clip_reward)
        self.returns = self.returns.masked_fill(dones, 0.0)
        return reward.float()


# ---------------------------------------------------------------------------- rollout buffer
class DeviceDictRolloutBuffer(DictRolloutBuffer):
    """SB3's ``DictRolloutBuffer`` as torch tensors on ``device``: ``add`` takes tensors, GAE runs
    on the device, and ``get`` yields :class:`DictRolloutBufferSamples` gathered on the device.

    Storage is ``(buffer_size, n_envs, ...)``; a sample index ``i`` follows SB3's flattened order
    (``env = i // buffer_size``, ``step = i % buffer_size``), gathered without a flattened copy.
    Keys in ``static_keys`` are stored once per env (the values of the rollout's first step)
    instead of once per step: for observations that never change within an env (a batched
    world's robot and task), which saves about 30% of the buffer.

    :param buffer_size: steps per env.
    :param observation_space: a ``Dict`` space.
    :param action_space: the action space.
    :param device: the device of every tensor (the env's and the policy's).
    :param gae_lambda: GAE's lambda.
    :param gamma: discount.
    :param n_envs: number of envs.
    :param static_keys: observation keys constant per env (see above).
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        gae_lambda: float = 1,
        gamma: float = 0.99,
        n_envs: int = 1,
        static_keys: Iterable[str] = (),
    ):
        self.static_keys = tuple(k for k in observation_space.spaces if k in set(static_keys))
        self._storage_ready = False
        super().__init__(buffer_size, observation_space, action_space, device, gae_lambda, gamma, n_envs)

    def reset(self) -> None:
        if not self._storage_ready:  # allocated once, reused by every rollout
            zeros = lambda *shape: th.zeros(shape, dtype=th.float32, device=self.device)  # noqa: E731
            t, n = self.buffer_size, self.n_envs
            self.observations = {k: zeros(t, n, *shape) for k, shape in self.obs_shape.items() if k not in self.static_keys}
            self.static_observations = {k: zeros(n, *self.obs_shape[k]) for k in self.static_keys}
            self.actions = zeros(t, n, self.action_dim)
            self.rewards, self.returns, self.episode_starts = zeros(t, n), zeros(t, n), zeros(t, n)
            self.values, self.log_probs, self.advantages = zeros(t, n), zeros(t, n), zeros(t, n)
            self._storage_ready = True
        self.generator_ready = False
        self.pos, self.full = 0, False

    def add(
        self,
        obs: Mapping[str, th.Tensor],
        action: th.Tensor,
        reward: th.Tensor,  # type: ignore[override]
        episode_start: th.Tensor,
        value: th.Tensor,
        log_prob: th.Tensor,
    ) -> None:
        """Store one step of every env (all arguments tensors on the device)."""
        for key, store in self.observations.items():
            store[self.pos].copy_(obs[key])
        if self.pos == 0:
            for key, store in self.static_observations.items():
                store.copy_(obs[key])
        self.actions[self.pos].copy_(action.reshape(self.n_envs, self.action_dim))
        self.rewards[self.pos].copy_(reward)
        self.episode_starts[self.pos].copy_(episode_start)
        self.values[self.pos].copy_(value.flatten())
        self.log_probs[self.pos].copy_(log_prob.flatten())
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True

    def compute_returns_and_advantage(self, last_values: th.Tensor, dones: th.Tensor) -> None:  # type: ignore[override]
        """GAE(lambda) advantages and TD(lambda) returns, as SB3's ``RolloutBuffer`` (on the device)."""
        last_values = last_values.detach().flatten().float()
        next_non_terminal, next_values = 1.0 - dones.float(), last_values
        advantage = th.zeros_like(last_values)
        for step in reversed(range(self.buffer_size)):
            if step < self.buffer_size - 1:
                next_non_terminal, next_values = 1.0 - self.episode_starts[step + 1], self.values[step + 1]
            delta = self.rewards[step] + self.gamma * next_values * next_non_terminal - self.values[step]
            advantage = delta + self.gamma * self.gae_lambda * next_non_terminal * advantage
            self.advantages[step] = advantage
        self.returns = self.advantages + self.values

    def get(self, batch_size: int | None = None) -> Generator[DictRolloutBufferSamples, None, None]:  # type: ignore[override]
        """Minibatches of ``batch_size`` samples (all when ``None``) in a random order drawn with
        torch's generator on the device."""
        assert self.full, "the rollout buffer is not full"
        total = self.buffer_size * self.n_envs
        indices = th.randperm(total, device=self.device)
        self.generator_ready = True
        batch_size = total if batch_size is None else batch_size
        for start in range(0, total, batch_size):
            yield self._get_samples(indices[start : start + batch_size])

    def _get_samples(self, batch_inds: th.Tensor, env=None) -> DictRolloutBufferSamples:  # type: ignore[override]
        env_index, step = batch_inds // self.buffer_size, batch_inds % self.buffer_size
        observations = {k: v[step, env_index] for k, v in self.observations.items()}
        observations.update({k: v[env_index] for k, v in self.static_observations.items()})
        return DictRolloutBufferSamples(
            observations={k: observations[k] for k in self.obs_shape},
            actions=self.actions[step, env_index],
            old_values=self.values[step, env_index],
            old_log_prob=self.log_probs[step, env_index],
            advantages=self.advantages[step, env_index],
            returns=self.returns[step, env_index],
        )

    def stacked_observations(self) -> dict[str, th.Tensor]:
        """Every key as ``(buffer_size, n_envs, ...)`` (static keys broadcast over the steps)."""
        out = dict(self.observations)
        out.update({k: v.expand(self.buffer_size, *v.shape) for k, v in self.static_observations.items()})
        return {k: out[k] for k in self.obs_shape}


# ---------------------------------------------------------------------------- episodes
class _DeviceEpisodes:
    """``VecMonitor``'s episode returns and lengths, kept in tensors; finished episodes are
    recorded per step on the device and handed over once per rollout."""

    def __init__(self, n_envs: int, device: th.device):
        self.returns = th.zeros(n_envs, dtype=th.float32, device=device)
        self.lengths = th.zeros(n_envs, dtype=th.long, device=device)
        self.t_start = time.time()
        self._finished: list[tuple[th.Tensor, th.Tensor, th.Tensor]] = []

    def step(self, reward: th.Tensor, dones: th.Tensor) -> None:
        self.returns += reward
        self.lengths += 1
        self._finished.append((dones, self.returns.clone(), self.lengths.clone()))
        self.returns.masked_fill_(dones, 0.0)
        self.lengths.masked_fill_(dones, 0)

    def flush(self, buffer: deque) -> None:
        """Append the episodes finished since the last flush to SB3's ``ep_info_buffer`` (one copy)."""
        if not self._finished:
            return
        dones, returns, lengths = (th.stack(parts).flatten() for parts in zip(*self._finished))
        self._finished.clear()
        ended = dones.nonzero().flatten()
        finished = th.stack([returns.index_select(0, ended).double(), lengths.index_select(0, ended).double()]).tolist()
        t = round(time.time() - self.t_start, 6)
        buffer.extend({"r": r, "l": int(n), "t": t} for r, n in zip(*finished))


# ---------------------------------------------------------------------------- measuring
class HostTransferCounter(TorchFunctionMode):
    """Counts, while active, the torch calls that cross between host and device, by kind (on
    CUDA each is a copy or a wait for the device; on a CPU-only machine they count what they
    would be on CUDA):

    * ``to_host``: ``.cpu()``, ``.numpy()`` (not after ``.cpu()``), ``.tolist()``, ``np.asarray``
      of a tensor -- with the bytes copied (``to_host_bytes``);
    * ``syncs``: scalar reads that wait for the device: ``.item()``, ``bool()``, ``float()``,
      ``int()``, ``nonzero`` and indexing with a boolean mask;
    * ``to_device``: tensors made from host data (``torch.as_tensor`` / ``torch.tensor`` of numpy
      arrays or lists) -- with their bytes (``to_device_bytes``);
    * ``calls``: every torch function called (on CUDA, an upper bound on the kernels launched
      outside Warp's graphs).

    Use as a context manager: ``with HostTransferCounter() as counter: ...; counter.counts``.
    """

    _TO_HOST = {"cpu", "numpy", "tolist", "__array__"}
    _SYNCS = {"item", "__bool__", "__float__", "__int__", "__index__", "nonzero"}
    _FROM_HOST = {"as_tensor", "tensor"}

    def __init__(self):
        super().__init__()
        self.counts = {"to_host": 0, "to_host_bytes": 0, "syncs": 0, "to_device": 0, "to_device_bytes": 0, "calls": 0}
        self._on_host: set[int] = set()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        result = func(*args, **kwargs)
        name = getattr(func, "__name__", "")
        self.counts["calls"] += 1
        first = args[0] if args else None
        if name in self._TO_HOST and isinstance(first, th.Tensor):
            if not (name in ("numpy", "tolist", "__array__") and id(first) in self._on_host):
                self.counts["to_host"] += 1
                self.counts["to_host_bytes"] += first.numel() * first.element_size()
            if name == "cpu":
                self._on_host.add(id(result))
        elif name in self._SYNCS:
            self.counts["syncs"] += 1
        elif (
            name in ("__getitem__", "__setitem__")
            and isinstance(args[1] if len(args) > 1 else None, th.Tensor)
            and args[1].dtype == th.bool
        ):
            self.counts["syncs"] += 1
        elif name in self._FROM_HOST and first is not None and not isinstance(first, th.Tensor):
            self.counts["to_device"] += 1
            if isinstance(result, th.Tensor):
                self.counts["to_device_bytes"] += result.numel() * result.element_size()
        return result


# ---------------------------------------------------------------------------- the algorithm
@contextmanager
def _tensor_explained_variance():
    """PPO.train computes the explained variance of the buffer's values with numpy; for device
    tensors it is computed in torch (one scalar copied)."""
    import stable_baselines3.ppo.ppo as sb3_ppo

    original = sb3_ppo.explained_variance

    def explained_variance(y_pred, y_true):
        if not isinstance(y_true, th.Tensor):
            return original(y_pred, y_true)
        var_y = y_true.var(unbiased=False)
        return float(th.where(var_y == 0, th.nan, 1 - (y_true - y_pred).var(unbiased=False) / var_y))

    sb3_ppo.explained_variance = explained_variance
    try:
        yield
    finally:
        sb3_ppo.explained_variance = original


@contextmanager
def _no_distribution_validation():
    """torch.distributions checks every distribution's parameters and samples (``Normal``: finite
    mean, positive scale, a real sample), each check a wait for the device; SB3's policies draw a
    distribution every forward. Off while DevicePPO collects and updates (NaNs still surface in
    the losses); the process default is restored afterwards."""
    previous = th.distributions.Distribution._validate_args
    th.distributions.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        th.distributions.Distribution.set_default_validate_args(previous)


def _same_device(a: th.device, b: th.device) -> bool:
    a, b = th.device(a), th.device(b)
    if a.type != b.type:
        return False
    if a.type != "cuda":
        return True
    current = th.cuda.current_device() if th.cuda.is_available() else 0
    return (a.index if a.index is not None else current) == (b.index if b.index is not None else current)


class DevicePPO(PPO):
    """SB3's PPO with device-native rollouts on a :class:`~unimal_envs.batched.BatchedUnimalEnv`
    (see the module docstring): same arguments, same ``train()``, saved and loaded as a normal
    SB3 model (``DevicePPO.load``; ``PPO.load`` reads it too).

    Device mode applies when the env is a ``BatchedUnimalEnv``, optionally wrapped in
    ``VecMonitor`` and one ``VecNormalize`` (:func:`device_env_chain`); with any other env the
    algorithm is SB3's PPO unchanged. In device mode the policy must live on the env's device
    (``device="auto"`` for both, or the same explicit device).

    :attr timings: seconds spent collecting rollouts (``"rollout"``) and in PPO's update
        (``"update"``), summed over this model's ``learn`` calls (CUDA is synchronised at the
        boundaries, so the split is the device's real split).

    :raises ValueError: (in device mode) the policy's device differs from the env's.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        self.timings = {"rollout": 0.0, "update": 0.0}
        self._device_state: dict[str, Any] = {}
        #: (device mode) the env's latest raw observation (before normalisation): what a DAgger
        #: teacher labels; set at every reset and step, before the step's callbacks run
        self.last_raw_obs: dict[str, th.Tensor] | None = None
        #: (device mode) ``(raw observation, actions) -> actions executed``: e.g. DAgger's teacher
        #: mixing; the rollout buffer keeps the policy's own actions
        self.executed_actions: Any = None
        super().__init__(*args, **kwargs)

    # ------------------------------------------------------------------ set-up
    def _device_chain(self):
        return device_env_chain(self.env)

    @property
    def device_mode(self) -> bool:
        """Whether this model collects its rollouts on the device: its env is a ``BatchedUnimalEnv``,
        optionally under ``VecMonitor`` and one ``VecNormalize`` (:func:`device_env_chain`)."""
        return self._device_chain() is not None

    @property
    def device_normalizer(self) -> DeviceNormalizer | None:
        """(device mode) The device mirror of the env's ``VecNormalize``, as of the latest rollout: it
        normalises raw observation tensors as the policy sees them. ``None`` when the env has no
        ``VecNormalize``, or before the first ``learn`` in device mode."""
        return self._device_state.get("normalizer")

    def _static_keys(self, chain) -> tuple[str, ...]:
        from unimal_envs.batched.env import STATIC_KEYS

        _, normalizer = chain
        normalized = set(normalizer.norm_obs_keys or ()) if normalizer is not None and normalizer.norm_obs else set()
        return tuple(k for k in STATIC_KEYS if k not in normalized)

    def _setup_model(self) -> None:
        chain = self._device_chain()
        kwargs = dict(self.rollout_buffer_kwargs or {})
        kwargs.pop("static_keys", None)
        if chain is not None:
            self.rollout_buffer_class = DeviceDictRolloutBuffer
            kwargs["static_keys"] = self._static_keys(chain)
        elif self.rollout_buffer_class is DeviceDictRolloutBuffer:  # loaded for another env
            self.rollout_buffer_class = None
        self.rollout_buffer_kwargs = kwargs
        super()._setup_model()
        if not hasattr(self, "timings"):  # loaded models skip __init__'s attributes
            self.timings = {"rollout": 0.0, "update": 0.0}
        if not hasattr(self, "executed_actions"):
            self.last_raw_obs, self.executed_actions = None, None
        self._device_state = {}

    def _check_device(self, benv) -> None:
        if not _same_device(self.device, benv.torch_device):
            raise ValueError(
                f"DevicePPO runs its policy on the batched env's tensors, but the policy is on {self.device} and the env "
                f"on {benv.torch_device}; build both on the same device (device='auto' for both, or the same explicit device)"
            )

    def _ensure_device_buffer(self, chain) -> None:
        buffer = self.rollout_buffer
        static = self._static_keys(chain)
        if not isinstance(buffer, DeviceDictRolloutBuffer) or buffer.static_keys != static or buffer.n_envs != self.n_envs:
            self.rollout_buffer_class = DeviceDictRolloutBuffer
            self.rollout_buffer_kwargs = {
                **{k: v for k, v in self.rollout_buffer_kwargs.items() if k != "static_keys"},
                "static_keys": static,
            }
            self.rollout_buffer = DeviceDictRolloutBuffer(
                self.n_steps,
                self.observation_space,
                self.action_space,
                device=self.device,
                gamma=self.gamma,
                gae_lambda=self.gae_lambda,
                n_envs=self.n_envs,
                **self.rollout_buffer_kwargs,
            )

    def _state(self, chain) -> dict[str, Any]:
        """The device-side state for this env chain (normaliser mirror, episode counters)."""
        benv, normalizer = chain
        state = self._device_state
        if state.get("env") is not benv or state.get("source") is not normalizer:
            state.clear()
            state.update(
                env=benv,
                source=normalizer,
                episodes=_DeviceEpisodes(benv.num_envs, benv.torch_device),
                normalizer=DeviceNormalizer(normalizer, benv.torch_device) if normalizer is not None else None,
            )
        return state

    def _excluded_save_params(self) -> list[str]:
        # device tensors and env references: rebuilt on the next learn (a fresh reset)
        return [
            *super()._excluded_save_params(),
            "_device_state",
            "_last_obs",
            "_last_episode_starts",
            "_last_original_obs",
            "timings",
            "last_raw_obs",
            "executed_actions",
        ]

    def _setup_learn(
        self, total_timesteps: int, callback=None, reset_num_timesteps: bool = True, tb_log_name: str = "run", progress_bar: bool = False
    ) -> tuple[int, BaseCallback]:
        chain = self._device_chain()
        if chain is None:
            return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        benv, _ = chain
        self._check_device(benv)
        self._ensure_device_buffer(chain)
        # As BaseAlgorithm._setup_learn, with the reset done through the torch interface.
        self.start_time = time.time_ns()
        if self.ep_info_buffer is None or reset_num_timesteps:
            self.ep_info_buffer = deque(maxlen=self._stats_window_size)
            self.ep_success_buffer = deque(maxlen=self._stats_window_size)
        if self.action_noise is not None:
            self.action_noise.reset()
        if reset_num_timesteps:
            self.num_timesteps = 0
            self._episode_num = 0
        else:
            total_timesteps += self.num_timesteps
        self._total_timesteps = total_timesteps
        self._num_timesteps_at_start = self.num_timesteps
        state = self._state(chain)
        on_device = isinstance(self._last_obs, dict) and all(isinstance(v, th.Tensor) for v in self._last_obs.values())
        if reset_num_timesteps or not on_device or state.get("last_env") is not benv:
            self._last_obs = self._reset_on_device(state)
            self._last_episode_starts = th.ones(benv.num_envs, device=benv.torch_device)
        if not self._custom_logger:
            self._logger = utils.configure_logger(self.verbose, self.tensorboard_log, tb_log_name, reset_num_timesteps)
        return total_timesteps, self._init_callback(callback, progress_bar)

    def _reset_on_device(self, state: dict[str, Any]) -> dict[str, th.Tensor]:
        benv, normalizer = state["env"], state["normalizer"]
        obs = benv.reset_tensors()
        self.last_raw_obs = obs
        state["episodes"] = _DeviceEpisodes(benv.num_envs, benv.torch_device)
        state["last_env"] = benv
        if normalizer is not None:
            normalizer.pull()
            obs = normalizer.reset(obs)
            normalizer.push()
        return obs

    # ------------------------------------------------------------------ rollouts
    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, rollout_buffer, n_rollout_steps: int) -> bool:
        """SB3's ``collect_rollouts`` on the device when the env allows it (see the class docstring)."""
        chain = device_env_chain(env)
        start = time.perf_counter()
        try:
            if chain is None:
                return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
            self._ensure_device_buffer(chain)
            with _no_distribution_validation():
                return self._collect_on_device(chain, callback, self.rollout_buffer, n_rollout_steps)
        finally:
            self._synchronize()
            self.timings["rollout"] += time.perf_counter() - start

    def _collect_on_device(self, chain, callback: BaseCallback, rollout_buffer: DeviceDictRolloutBuffer, n_rollout_steps: int) -> bool:
        benv, _ = chain
        state = self._state(chain)
        normalizer, episodes = state["normalizer"], state["episodes"]
        assert isinstance(self._last_obs, dict), "No previous observation was provided"
        self.policy.set_training_mode(False)
        if "bounds" not in state:
            state["bounds"] = tuple(th.as_tensor(b, device=benv.torch_device) for b in (self.action_space.low, self.action_space.high))
        low, high = state["bounds"]
        if normalizer is not None:
            normalizer.pull()

        n_steps = 0
        rollout_buffer.reset()
        if self.use_sde:
            self.policy.reset_noise(benv.num_envs)
        callback.on_rollout_start()

        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                self.policy.reset_noise(benv.num_envs)
            with th.no_grad():
                actions, values, log_probs = self.policy(self._last_obs)
            if self.policy.squash_output:
                clipped_actions = low + 0.5 * (actions + 1.0) * (high - low)
            else:
                clipped_actions = th.clamp(actions, low, high)
            if self.executed_actions is not None:
                clipped_actions = self.executed_actions(self.last_raw_obs, clipped_actions)

            new_obs, rewards, terminated, truncated, infos = benv.step_tensors(clipped_actions)
            self.last_raw_obs = new_obs
            dones = terminated | truncated
            episodes.step(rewards, dones)
            if normalizer is not None:
                new_obs = normalizer.observe(new_obs)
                rewards = normalizer.reward(rewards, dones)
            else:
                rewards = rewards.float()

            self.num_timesteps += benv.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                if normalizer is not None:
                    normalizer.push()
                return False
            n_steps += 1

            # Time-limit truncation: bootstrap with the value of the final observation (as SB3's PPO does).
            truncated_worlds = truncated.nonzero().flatten()  # the step's one wait for the device
            if truncated_worlds.numel():
                final = {k: v.index_select(0, truncated_worlds) for k, v in infos["final_observation"].items()}
                if normalizer is not None:
                    final = normalizer.normalize_obs(final)
                with th.no_grad():
                    terminal_values = self.policy.predict_values(final).flatten()
                rewards = rewards.index_add(0, truncated_worlds, self.gamma * terminal_values)

            rollout_buffer.add(self._last_obs, actions, rewards, self._last_episode_starts, values, log_probs)
            self._last_obs = new_obs
            self._last_episode_starts = dones.float()

        with th.no_grad():
            values = self.policy.predict_values(new_obs)
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        if normalizer is not None:
            normalizer.push()
        episodes.flush(self.ep_info_buffer)

        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    # ------------------------------------------------------------------ update
    def train(self) -> None:
        """SB3's PPO update (on device tensors when the buffer holds them)."""
        start = time.perf_counter()
        try:
            if isinstance(self.rollout_buffer, DeviceDictRolloutBuffer):
                with _tensor_explained_variance(), _no_distribution_validation():
                    super().train()
            else:
                super().train()
        finally:
            self._synchronize()
            self.timings["update"] += time.perf_counter() - start

    def _synchronize(self) -> None:
        if self.device.type == "cuda":
            th.cuda.synchronize(self.device)
