"""Synthetic observation batches with consistent masks, for tests and benchmarks (no simulator)."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from sb3_divmorph.nn.extractors import ACT_PADDING_MASK, CONTEXT, OBS_PADDING_MASK, PROPRIOCEPTIVE, TASK_EMBEDDING


def random_observations(
    observation_space: spaces.Dict,
    batch_size: int,
    seed: int = 0,
    n_morphologies: int | None = None,
    n_tasks: int | None = None,
    min_tokens: int = 2,
) -> dict[str, np.ndarray]:
    """Sample a batch from the space, then make it look like states of real robots.

    Every robot has ``n`` real tokens (torso + limbs, ``min_tokens <= n <= L``): padded token rows of
    ``proprioceptive`` and ``context`` are zero and flagged in ``obs_padding_mask``. The torso has no
    hinge and each limb one or two, flagged in ``act_padding_mask`` (1.0 = padded). A robot's
    ``context`` and masks are fixed, and so is a task's ``task_embedding``; samples draw a robot
    from a pool of ``n_morphologies`` and a task from a pool of ``n_tasks`` (``None``: every
    sample its own), like a minibatch of a multi-robot rollout.

    :param observation_space: the UNIMAL ``spaces.Dict``.
    :param batch_size: samples.
    :param seed: seed of the sampler.
    :param n_morphologies: distinct robots in the batch (``None`` = ``batch_size``).
    :param n_tasks: distinct task embeddings in the batch (``None`` = ``batch_size``).
    :param min_tokens: fewest real tokens per robot.
    :return: dict of float32 arrays with a leading batch dimension.
    """
    rng = np.random.default_rng(seed)
    observation_space.seed(int(rng.integers(2**31)))
    obs = {key: np.stack([space.sample() for _ in range(batch_size)]) for key, space in observation_space.spaces.items()}
    tokens_shape, mask_shape = observation_space[PROPRIOCEPTIVE].shape, observation_space[ACT_PADDING_MASK].shape
    assert tokens_shape is not None and mask_shape is not None  # Box spaces have a shape
    n_tokens = tokens_shape[0]
    slots = mask_shape[0] // n_tokens

    robot = rng.integers(n_morphologies, size=batch_size) if n_morphologies else np.arange(batch_size)
    n_robots = int(robot.max()) + 1
    real_tokens = rng.integers(min_tokens, n_tokens + 1, size=n_robots)[robot]
    token_padded = np.arange(n_tokens)[None, :] >= real_tokens[:, None]
    # hinges: none on the torso, the first slot of every limb, the second slot on about half
    slot_real = np.zeros((n_robots, n_tokens, slots), dtype=bool)
    slot_real[:, 1:, 0] = True
    if slots > 1:
        slot_real[:, 1:, 1:] = rng.random((n_robots, n_tokens - 1, slots - 1)) < 0.5
    slot_real = slot_real[robot] & ~token_padded[..., None]

    obs[PROPRIOCEPTIVE] = np.where(token_padded[..., None], 0.0, obs[PROPRIOCEPTIVE])
    if CONTEXT in obs:
        obs[CONTEXT] = np.where(token_padded[..., None], 0.0, obs[CONTEXT][robot])
    if TASK_EMBEDDING in obs and n_tasks:
        obs[TASK_EMBEDDING] = obs[TASK_EMBEDDING][rng.integers(n_tasks, size=batch_size)]
    obs[OBS_PADDING_MASK] = token_padded
    obs[ACT_PADDING_MASK] = ~slot_real.reshape(batch_size, -1)
    return {key: np.asarray(value, dtype=np.float32) for key, value in obs.items()}
