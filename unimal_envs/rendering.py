"""Videos and pictures of UNIMAL robots (headless: ``MUJOCO_GL=egl``)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path

import gymnasium as gym
import numpy as np


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: int = 50) -> Path:
    """Encode RGB frames (H, W, 3, uint8) as an H.264 MP4 with imageio/ffmpeg.

    The file is written under a temporary name and renamed, so an interrupted call never leaves
    a truncated video behind.

    :param frames: the frames, all the same size.
    :param path: output ``.mp4`` path (parent folders are created).
    :param fps: frames per second (50 = real time for the envs' 0.02 s control step).
    :returns: the path written.
    """
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    # macro_block_size=1 keeps odd frame sizes as they are instead of resizing with a warning.
    with imageio.get_writer(partial, fps=fps, codec="libx264", macro_block_size=1, quality=7) as writer:
        count = 0
        for frame in frames:
            writer.append_data(np.asarray(frame))
            count += 1
    if count == 0:
        partial.unlink(missing_ok=True)
        raise ValueError(f"no frames to write to {path}")
    os.replace(partial, path)
    return path


def record_episode(
    env: gym.Env,
    policy: Callable[[dict], np.ndarray] | None = None,
    steps: int = 200,
    seed: int | None = None,
    options: dict | None = None,
) -> tuple[list[np.ndarray], float]:
    """Roll out one episode (up to ``steps``) in an ``rgb_array`` env and collect its frames.

    :param env: an env made with ``render_mode="rgb_array"``.
    :param policy: maps an observation to an action; random actions when ``None``.
    :param steps: maximum number of steps.
    :param seed: reset seed.
    :param options: reset options, e.g. ``{"morphology": name}``.
    :returns: the frames (first one before any step) and the undiscounted return.
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"record_episode needs an env made with render_mode='rgb_array', got {env.render_mode!r}")
    obs, _ = env.reset(seed=seed, options=options)
    frames, total = [env.render()], 0.0
    for _ in range(steps):
        action = env.action_space.sample() if policy is None else policy(obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        frames.append(env.render())
        if terminated or truncated:
            break
    return frames, total
