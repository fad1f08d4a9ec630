"""Deterministic evaluation on the batched backend: every episode of every robot at once, as one world each.

The evaluation curves of a transfer run (:class:`~divmorph.pipeline.curves.EvalCurveCallback`)
play each robot's episodes one after another in a C-MuJoCo env of its own. Evaluating against many
draws -- 15 episodes of 40 robots at every curve point, which heavy-tailed tasks such as PointNav
need -- then costs as much as the training between two points. On the
batched backend the same evaluation is one rollout of ``robots x episodes`` MuJoCo Warp worlds: world
``i`` plays episode ``i % episodes`` of robot ``i // episodes`` until its first end, and the rollout
stops when every world has ended once.

What it shares with the single-env evaluation: the deterministic (mean) action clipped to the action
space, the model's observation statistics as they are (used, never updated), the raw task reward summed over the episode, the
1000-step truncation, and the same episodes at every call (the env's generator is seeded again).
What differs, because batching imposes it: float32 physics, terrain drawn from
the env's pool of variants, and episodes drawn by the env's own generator, so a robot's episodes
depend on the robots evaluated beside it. Curves evaluated this way are comparable with each other
(every arm and point of a race), not episode for episode with single-env numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.device_ppo import DeviceNormalizer
from divmorph.pipeline.envs import batched_env


def make_evaluation_env(
    env_name: str,
    robots: list[Path],
    episodes: int,
    max_steps: int,
    seed: int,
    device: str,
    terrain_variants: int,
    **env_kwargs: Any,
):
    """The batched env of one evaluation: ``episodes`` worlds of each of ``robots``.

    :param env_name: the task's env id (``Unimal-PointNav-v0``).
    :param env_kwargs: further :func:`~unimal_envs.batched.make_batched_env` arguments (``instruction``,
        ``height_reference``).
    """
    return batched_env(env_name, episodes, device, seed, terrain_variants, max_steps, morphologies=list(robots), **env_kwargs)


@th.no_grad()
def batched_returns(model: BaseAlgorithm, env, normalizer: VecNormalize | None, seed: int) -> list[dict[str, Any]]:
    """The first episode of every world of ``env`` under ``model``'s deterministic policy.

    :param env: a :class:`~unimal_envs.batched.BatchedUnimalEnv` (:func:`make_evaluation_env`).
    :param normalizer: the model's observation statistics (used, never updated), or ``None``.
    :param seed: seeds the env's generator first, so that every call plays the same episodes.
    :returns: ``[{"robot", "episode", "return", "length"}]`` per world, as
        :func:`~divmorph.pipeline.curves.rollout_returns` gives them.
    """
    device = env.torch_device
    normalize = DeviceNormalizer(normalizer, device).normalize_obs if normalizer is not None else None
    policy = model.policy
    was_training = policy.training
    policy.set_training_mode(False)
    space = model.action_space
    assert isinstance(space, spaces.Box), "the UNIMAL envs' actions are a Box"
    low, high = (th.as_tensor(bound, device=device) for bound in (space.low, space.high))
    env.seed(seed)
    obs = env.reset_tensors()
    n = env.num_envs
    returns = th.zeros(n, dtype=th.float64, device=device)
    lengths = th.zeros(n, dtype=th.long, device=device)
    running = th.ones(n, dtype=th.bool, device=device)
    try:
        while bool(running.any()):
            features = normalize(obs) if normalize is not None else obs
            features = {key: value.to(policy.device) for key, value in features.items()}
            actions = policy._predict(features, deterministic=True).to(device)
            obs, reward, terminated, truncated, _ = env.step_tensors(th.clamp(actions, low, high))
            returns += reward.double() * running
            lengths += running.long()
            running &= ~(terminated | truncated)
    finally:
        policy.set_training_mode(was_training)
    per_robot = env.worlds_per_robot
    return [
        {"robot": env.morphology_names[i], "episode": i % per_robot, "return": float(returns[i]), "length": int(lengths[i])}
        for i in range(n)
    ]
