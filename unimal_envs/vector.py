"""Many Unimal worlds behind one Stable-Baselines3 ``VecEnv`` call, without the layers around each.

``VecMonitor(DummyVecEnv([lambda: gym.make(id, max_episode_steps=T), ...]))`` -- SB3's usual stack --
spends as much time around the physics as in it at 4-16 envs: Gymnasium's checker, order and time-limit
wrappers on every step, a deep copy of every observation dict and of every info dict per step, then
VecMonitor's pass over the results. :class:`UnimalVecEnv` steps the raw envs, counts the time limit and
the episode statistics itself and hands out fresh arrays, so nothing needs copying twice. Its
trajectories are those of that stack for the same seeds, robots and actions, resets included
(``tests/test_vector_env.py``); its infos carry the same ``TimeLimit.truncated``,
``terminal_observation`` and ``episode`` (``r``, ``l``, ``t``) entries.

    from unimal_envs.vector import make_unimal_vec_env
    venv = make_unimal_vec_env("Unimal-FT-v0", n_envs=4, seed=0, max_episode_steps=1000)

rl-zoo runs the shipped entries through it too (their ``vec_env_wrapper``: :func:`lean_vec_env`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn


class UnimalVecEnv(VecEnv):
    """Steps ``n`` envs in one call and writes their observations side by side (SB3's ``VecEnv`` API).

    It stands in for ``VecMonitor(DummyVecEnv(env_fns))`` whose envs had ``TimeLimit(max_episode_steps)``:
    the envs ``env_fns`` make should be unwrapped ones (``gym.make(...).unwrapped``, or a wrapper of one
    whose ``reset``/``step`` matter, such as the evaluation's episode seeding); the time limit and the
    episode statistics are counted here. ``env_is_wrapped(Monitor)`` answers True for every env: each
    finished episode's info has Monitor's ``episode`` entry, which is what SB3's ``evaluate_policy``
    looks for.

    :param env_fns: one function per env, each making a new env (Dict observations, Box actions).
    :param max_episode_steps: truncate an episode after this many steps (``None``: never).
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], max_episode_steps: int | None = None):
        self.envs = [fn() for fn in env_fns]
        if len({id(env.unwrapped) for env in self.envs}) != len(self.envs):
            raise ValueError("env_fns returned the same env more than once; each function must make a new env")
        first = self.envs[0]
        if not isinstance(first.observation_space, spaces.Dict):
            raise TypeError(f"UnimalVecEnv takes envs with Dict observations; got {first.observation_space}")
        super().__init__(len(self.envs), first.observation_space, first.action_space)
        self.max_episode_steps = max_episode_steps
        self._spaces: list[tuple[str, tuple[int, ...], Any]] = [
            (key, tuple(space.shape or ()), space.dtype) for key, space in first.observation_space.spaces.items()
        ]
        self._steps = np.zeros(self.num_envs, dtype=np.int64)
        self._returns = np.zeros(self.num_envs, dtype=np.float32)
        self._start = time.time()
        self.metadata = first.metadata
        self._actions: np.ndarray | None = None

    # -- the hot path ---------------------------------------------------------------------------------
    def _new_buffers(self) -> dict[str, np.ndarray]:
        return {key: np.empty((self.num_envs, *shape), dtype=dtype) for key, shape, dtype in self._spaces}

    def reset(self) -> VecEnvObs:
        buffers = self._new_buffers()
        for i, env in enumerate(self.envs):
            options = {"options": self._options[i]} if self._options[i] else {}
            obs, self.reset_infos[i] = env.reset(seed=self._seeds[i], **options)
            for key in buffers:
                buffers[key][i] = obs[key]
        self._reset_seeds()
        self._reset_options()
        self._steps[:] = 0
        self._returns[:] = 0.0
        return buffers

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        buffers = self._new_buffers()
        rewards = np.empty(self.num_envs, dtype=np.float32)
        dones = np.empty(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = []
        actions = self._actions
        assert actions is not None, "step_async comes before step_wait"
        self._steps += 1
        for i, env in enumerate(self.envs):
            obs, reward, terminated, truncated, info = env.step(actions[i])
            rewards[i] = reward
            truncated = truncated or (self.max_episode_steps is not None and self._steps[i] >= self.max_episode_steps)
            done = dones[i] = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            # the sum as VecMonitor keeps it: float32, after the float32 reward is stored
            self._returns[i] += rewards[i]
            if done:
                info["terminal_observation"] = obs
                # an env of its own Monitor (rl-zoo's) keeps Monitor's record, as it would under DummyVecEnv
                info.setdefault("episode", {"r": self._returns[i], "l": np.int32(self._steps[i]), "t": round(time.time() - self._start, 6)})
                self._returns[i] = 0.0
                self._steps[i] = 0
                obs, self.reset_infos[i] = env.reset()
            for key in buffers:
                buffers[key][i] = obs[key]
            infos.append(info)
        return buffers, rewards, dones, infos

    # -- the rest of the VecEnv API --------------------------------------------------------------------
    def close(self) -> None:
        for env in self.envs:
            env.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [env.render() for env in self.envs]  # type: ignore[misc]

    def _targets(self, indices: VecEnvIndices) -> list[gym.Env]:
        return [self.envs[i] for i in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [env.get_wrapper_attr(attr_name) for env in self._targets(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for env in self._targets(indices):
            setattr(env, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any) -> list[Any]:
        return [env.get_wrapper_attr(method_name)(*method_args, **method_kwargs) for env in self._targets(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        from stable_baselines3.common.env_util import is_wrapped

        # Monitor's episode statistics are built in (see the class docstring)
        return [wrapper_class is Monitor or is_wrapped(env, wrapper_class) for env in self._targets(indices)]


def make_unimal_vec_env(
    env_id: str,
    n_envs: int,
    seed: int | None = None,
    max_episode_steps: int | None = None,
    wrapper: Callable[[gym.Env, int], gym.Env] | None = None,
    **env_kwargs: Any,
) -> UnimalVecEnv:
    """``n_envs`` envs of a registered id in one :class:`UnimalVecEnv`, seeded ``seed + i`` at the first reset
    (as SB3's ``make_vec_env`` + ``VecMonitor`` would).

    :param env_id: a ``Unimal-*`` id (or any id whose env has Dict observations).
    :param max_episode_steps: the time limit (``None``: the id's registered one, if any).
    :param wrapper: ``(env, index) -> env`` applied to each raw env (e.g. per-episode seeding).
    :param env_kwargs: the env's arguments (``morphologies``, ``instruction``, ...).
    """
    if max_episode_steps is None:
        max_episode_steps = gym.spec(env_id).max_episode_steps

    def factory(index: int) -> Callable[[], gym.Env]:
        def make() -> gym.Env:
            env = gym.make(env_id, disable_env_checker=True, **env_kwargs).unwrapped
            return wrapper(env, index) if wrapper else env

        return make

    venv = UnimalVecEnv([factory(i) for i in range(n_envs)], max_episode_steps)
    if seed is not None:
        venv.seed(seed)
    return venv


def lean_vec_env(venv: VecEnv) -> VecEnv:
    """rl-zoo's ``vec_env_wrapper`` for the Unimal entries (``zoo_configs/ppo.yml``): the envs of the
    ``DummyVecEnv`` rl-zoo made (each in its ``Monitor``, which keeps writing rl-zoo's logs), stepped by a
    :class:`UnimalVecEnv` instead -- the same trajectories without the deep copies. Any other ``VecEnv``
    (``--vec-env subproc``) is returned as it is.
    """
    if type(venv) is not DummyVecEnv:
        return venv

    def keep(env: gym.Env) -> Callable[[], gym.Env]:
        return lambda: env

    lean = UnimalVecEnv([keep(env) for env in venv.envs])
    lean._seeds, lean._options = list(venv._seeds), list(venv._options)
    return lean
