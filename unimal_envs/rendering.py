"""Videos and pictures of UNIMAL robots (headless: ``MUJOCO_GL=egl``)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import cast

import gymnasium as gym
import numpy as np

#: Frames per second of a GIF (a GIF of every 50 fps frame would be large and slow in browsers).
GIF_FPS = 10


def frames_kept(frames: int, path: str | Path, fps: int = 50) -> int:
    """How many of ``frames`` rendered frames :func:`write_video` puts in ``path`` (a GIF keeps every
    ``fps / GIF_FPS``-th)."""
    if Path(path).suffix.lower() != ".gif":
        return frames
    stride = _gif_stride(fps)
    return (frames + stride - 1) // stride


def _gif_stride(fps: int) -> int:
    return max(1, round(fps / GIF_FPS))


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: int = 50) -> Path:
    """Encode RGB frames (H, W, 3, uint8) as an H.264 MP4 with imageio/ffmpeg, or as an animated
    GIF when ``path`` ends in ``.gif`` (every ``fps // GIF_FPS``-th frame, still real time: small
    enough for a README).

    The file is written under a temporary name and renamed, so an interrupted call never leaves
    a truncated video behind.

    :param frames: the frames, all the same size.
    :param path: output ``.mp4`` or ``.gif`` path (parent folders are created).
    :param fps: frames per second (50 = real time for the envs' 0.02 s control step).
    :returns: the path written.
    """
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    if path.suffix.lower() == ".gif":
        stride = _gif_stride(fps)
        writer = imageio.get_writer(partial, format="GIF", mode="I", duration=1000 * stride / fps, loop=0)
        frames = (frame for i, frame in enumerate(frames) if i % stride == 0)
    else:
        # macro_block_size=1 keeps odd frame sizes as they are instead of resizing with a warning.
        writer = imageio.get_writer(partial, fps=fps, codec="libx264", macro_block_size=1, quality=7)
    count = 0
    try:
        with writer:
            for frame in frames:  # frames may be a generator: each is encoded as it comes, none kept
                writer.append_data(np.asarray(frame))
                count += 1
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    if count == 0:
        partial.unlink(missing_ok=True)
        raise ValueError(f"no frames to write to {path}")
    os.replace(partial, path)
    return path


def episode_frames(
    env: gym.Env,
    policy: Callable[[dict], np.ndarray] | None = None,
    steps: int = 200,
    seed: int | None = None,
    options: dict | None = None,
    outcome: dict | None = None,
) -> Iterator[np.ndarray]:
    """Roll out one episode (up to ``steps``) in an ``rgb_array`` env, yielding each frame as it is
    rendered (the first one before any step), so a long video streams to :func:`write_video`
    without holding its frames in memory.

    :param env: an env made with ``render_mode="rgb_array"``.
    :param policy: maps an observation to an action; random actions when ``None``.
    :param steps: maximum number of steps.
    :param seed: reset seed.
    :param options: reset options, e.g. ``{"morphology": name}``.
    :param outcome: filled at the end with ``return`` (undiscounted) and ``steps``.
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"episode_frames needs an env made with render_mode='rgb_array', got {env.render_mode!r}")
    outcome = {} if outcome is None else outcome
    obs, _ = env.reset(seed=seed, options=options)
    total, taken = 0.0, 0
    yield cast(np.ndarray, env.render())  # rgb_array mode (checked above): a frame
    for _ in range(steps):
        action = env.action_space.sample() if policy is None else policy(obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        taken += 1
        yield cast(np.ndarray, env.render())
        if terminated or truncated:
            break
    outcome.update({"return": total, "steps": taken})


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
    outcome: dict = {}
    frames = list(episode_frames(env, policy, steps, seed, options, outcome))
    return frames, outcome["return"]
