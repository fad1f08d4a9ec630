"""The envs and observation statistics of a stage: vectorised envs from a profile, inherited
``VecNormalize`` statistics, device and seeding."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecEnv, VecMonitor
from sb3_divmorph.algos.vec_normalize import LeanVecNormalize

import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from sb3_divmorph.algos.finetune import freeze_observation_statistics
from divmorph.pipeline.config import ConfigError, Profile
from unimal_envs import env_id, task_of
from unimal_envs.vector import make_unimal_vec_env

from divmorph.pipeline.files import NORMALIZER


def make_vec_env(
    env_name: str,
    n_envs: int,
    seed: int,
    max_episode_steps: int,
    backend: str = "single",
    worlds_per_robot: int = 16,
    device: str = "cpu",
    terrain_variants: int = 64,
    **env_kwargs: Any,
) -> VecEnv:
    """The monitored training envs of a stage.

    ``backend="single"``: ``n_envs`` C-MuJoCo envs in one process (torch stays in this process),
    seeded ``seed + i``, stepped by one :class:`~unimal_envs.vector.UnimalVecEnv`.
    ``backend="batched"``: one MuJoCo Warp env with ``worlds_per_robot`` worlds of every robot on
    ``device`` and a pool of ``terrain_variants`` terrains per terrain task
    (:func:`unimal_envs.batched.make_batched_env`; ``n_envs`` unused).
    """
    if backend == "batched":
        return VecMonitor(batched_env(env_name, worlds_per_robot, device, seed, terrain_variants, max_episode_steps, **env_kwargs))

    # One UnimalVecEnv (the trajectories of VecMonitor(DummyVecEnv([gym.make(...)])), without their per-step
    # copies); each env is also reset with its seed once when made, as the pipeline always did.
    def first_reset(env: gym.Env, rank: int) -> gym.Env:
        env.reset(seed=seed + rank)
        return env

    return make_unimal_vec_env(env_name, n_envs, seed, max_episode_steps, wrapper=first_reset, **env_kwargs)


def batched_env(
    env_name: str, worlds_per_robot: int, device: str, seed: int, terrain_variants: int, max_episode_steps: int, **env_kwargs: Any
):
    """The MuJoCo Warp env of a task given by its env id (:func:`unimal_envs.batched.make_batched_env`;
    ``env_kwargs``: ``morphologies``, ``instruction``, ``height_reference``...)."""
    from unimal_envs.batched import make_batched_env

    task = task_of(env_name)
    return make_batched_env(
        task,
        worlds_per_robot=worlds_per_robot,
        device=device,
        seed=seed,
        terrain_variants=terrain_variants,
        max_episode_steps=max_episode_steps,
        **env_kwargs,
    )


def profile_env_kwargs(profile: Profile) -> dict[str, Any]:
    """The env arguments every env of a run takes from its profile (``height_reference``,
    ``goal_range``); empty at the defaults, so envs and backends that predate them are made exactly as before."""
    kwargs: dict[str, Any] = {} if profile.height_reference == "world" else {"height_reference": profile.height_reference}
    if profile.goal_range is not None:
        kwargs["goal_range"] = float(profile.goal_range)
    return kwargs


def task_env_name(task: str) -> str:
    return env_id(task)


def resolve_device(device: str) -> str:
    """The torch device a profile's ``device`` resolves to on this machine.

    :raises ConfigError: ``cuda`` requested where no CUDA device exists (training would otherwise
        silently run on the CPU while the records said cuda).
    """
    if device == "auto":
        return "cuda" if th.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not th.cuda.is_available():
        raise ConfigError(f"device {device!r} requested but this machine has no CUDA device; use cpu or auto")
    return device


def trained_env_settings(venv: VecEnv | None) -> dict[str, Any]:
    """What a model's envs were made with, read from the envs themselves: the observation setting
    ``height_reference`` and the robots (names of the first env's robots); empty when the envs do
    not tell (the batched backend, a foreign env)."""
    if venv is None:
        return {}
    try:
        height = venv.get_attr("height_reference")[0]
        robots = [m.name for m in venv.get_attr("morphologies")[0]]
    except (AttributeError, IndexError, TypeError):
        return {}
    return {"height_reference": height, "robots": robots}


def normalizer_for(venv: VecEnv, normalize: dict[str, Any] | None, gamma: float) -> VecEnv:
    """Wrap in ``VecNormalize`` with rl-zoo's ``normalize`` kwargs (``None``: no normalisation)."""
    if normalize is None:
        return venv
    return LeanVecNormalize(venv, gamma=gamma, **normalize)


def seed_everything(seed: int, threads: int) -> None:
    th.set_num_threads(max(1, threads))
    np.random.seed(seed)
    th.manual_seed(seed)


def robot_observations(
    env_name: str, robots: list[Path], seed: int = 0, instruction: str | None = None, **env_kwargs: Any
) -> dict[str, np.ndarray]:
    """One reset observation per robot, batched (for gates and selections).

    :param env_kwargs: further env arguments (e.g. the run's ``height_reference``).
    """
    import gymnasium as gym

    settings: dict[str, Any] = {**({"instruction": instruction} if instruction else {}), **env_kwargs}
    env = gym.make(env_name, morphologies=robots, **settings)
    try:
        observations = [env.reset(seed=seed, options={"morphology": i})[0] for i in range(len(robots))]
    finally:
        env.close()
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


def inherited_normalizer(source: Path, venv: VecEnv, gamma: float, freeze_observations: bool = False) -> VecEnv:
    """``venv`` wrapped in the observation statistics saved in ``source`` (if any); rewards are
    normalised afresh for the new task (their statistics learn).

    :param source: the folder of the trained model whose ``vecnormalize.pkl`` is inherited.
    :param venv: the new task's envs.
    :param gamma: the new run's discount (for the reward statistics).
    :param freeze_observations: keep the observation statistics exactly as inherited
        (:func:`~sb3_divmorph.algos.finetune.freeze_observation_statistics`): transfer does, so that the
        inputs of the weights it starts from do not move under them. ``False`` (GRL's evolution,
        where a child trains every layer on a training task) lets them go on learning.
    """
    if not (source / NORMALIZER).is_file():
        return venv
    normalizer = LeanVecNormalize.load(str(source / NORMALIZER), venv)
    normalizer.training, normalizer.norm_reward = True, True
    normalizer.gamma = gamma
    normalizer.ret_rms = RunningMeanStd(shape=())
    normalizer.returns = np.zeros(venv.num_envs)
    if freeze_observations:
        freeze_observation_statistics(normalizer)
    return normalizer
