"""Render one frame of every task into a picture (``results/tasks.png``).

Usage: ``python -m unimal_envs.gallery [--out results/tasks.png] [--morphology train-000]``
"""

from __future__ import annotations

import argparse
import io
import math
from pathlib import Path
from typing import cast

import gymnasium as gym
import mujoco
import numpy as np

import unimal_envs
import unimal_envs.morphology
from unimal_envs.tasks import TASKS


def _place(env, x: float, y: float, heading: float) -> None:
    """Put the robot at (x, y) on the ground (its spawn height above it), facing ``heading`` (deg)."""
    base = env.unwrapped
    data = base.data
    q = base.robot.indices().qpos.start
    half = math.radians(heading) / 2
    data.qpos[q : q + 3] = (x, y, base.arena.ground_height(x, y) + base.morphology.torso_height)
    if base.task.name not in ("Incline", "PushBoxIncline"):  # those spawn tilted with the slope
        data.qpos[q + 3 : q + 7] = (math.cos(half), 0.0, 0.0, math.sin(half))
    data.qvel[:] = 0.0


def _heading(origin, target) -> float:
    return math.degrees(math.atan2(target[1] - origin[1], target[0] - origin[0]))


def stage(env, task: str) -> None:
    """Place the robot and the tracking camera so that the frame shows what the task is about:
    the terrain or blocks ahead, the slope, the goal marker, the box and its goal, the walls."""
    base = env.unwrapped
    distance, azimuth, elevation = 6.0, 20.0, -20.0
    if task == "VT":  # just before the first terrain segment, looking along the course
        heights = base.arena.grid.heights[base.arena.grid.heights.shape[0] // 2]
        first = base.arena.grid.x0 + 0.1 * int(np.argmax(heights > 0.05))
        _place(env, first - 2.0, 0.0, 0.0)
        distance, elevation = 9.0, -18.0
    elif task == "Obstacle":  # in front of the first blocks, looking down the course
        _place(env, 6.0, 0.0, 0.0)
        distance, elevation = 11.0, -25.0
    elif task in ("Incline", "PushBoxIncline"):  # from the side, so the slope shows
        azimuth, elevation, distance = 75.0, -12.0, 8.0
        if task == "PushBoxIncline":
            box = base.data.xpos[base.task._box]
            _place(env, box[0] - 1.5, box[1], 0.0)
    elif task in ("Patrol", "PointNav"):  # a few metres before the goal marker, facing it
        goal = base.task.goal
        start = (0.0, 0.0) if task == "PointNav" else (-5.0, 0.0)
        toward = _heading(start, goal)
        x, y = goal[0] - 4.0 * math.cos(math.radians(toward)), goal[1] - 4.0 * math.sin(math.radians(toward))
        _place(env, x, y, toward)
        azimuth, distance, elevation = toward, 9.0, -30.0
    elif task == "ManipulateBox":  # behind the box, looking past it towards the goal marker
        # (box and goal are often 20-30 m apart: a camera framing both shows neither robot nor box)
        box = base.data.xpos[base.task._box]
        goal = base.task.goal
        toward = _heading(box, goal)
        _place(env, box[0] - 1.5 * math.cos(math.radians(toward)), box[1] - 1.5 * math.sin(math.radians(toward)), toward)
        mujoco.mj_forward(base.model, base.data)
        base.camera_offset = tuple(box - base.data.xpos[base.robot.torso_id])  # aim at the box, the robot in front of it
        azimuth, distance, elevation = toward, 7.0, -20.0
    elif task == "Exploration":  # near a corner of the walled square
        _place(env, 44.0, 44.0, 45.0)
        azimuth, distance, elevation = 45.0, 12.0, -30.0
    elif task == "Escape":  # on the bowl's floor, looking out at its rim
        _place(env, 8.0, 0.0, 0.0)
        distance, elevation = 8.0, -6.0
    base.camera_distance, base.camera_angles = distance, (azimuth, elevation)
    mujoco.mj_forward(base.model, base.data)
    base.robot.sync()


def render_tasks(
    morphology: str, width: int = 400, height: int = 300, seed: int = 0, morphologies: str = "train"
) -> list[tuple[str, np.ndarray]]:
    """One frame per task, staged by :func:`stage` to show the task's arena and props.

    :param morphology: the robot's name in ``morphologies``.
    :param morphologies: the robot set (a set name or folder, as for :class:`~unimal_envs.env.UnimalEnv`).
    """
    files = [p for p in unimal_envs.morphology.morphology_files(morphologies) if p.stem == morphology]
    if not files:
        raise ValueError(f"no robot {morphology!r} in the set {morphologies!r}")
    frames = []
    for task in TASKS:
        env = gym.make(unimal_envs.env_id(task), morphologies=files, render_mode="rgb_array", width=width, height=height)
        env.reset(seed=seed)
        stage(env, task)
        frames.append((task, cast(np.ndarray, env.render())))  # an rgb_array frame
        env.close()
    return frames


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Render one frame of every UNIMAL task into a grid picture.")
    parser.add_argument("--out", type=Path, default=Path("results/tasks.png"))
    parser.add_argument("--morphology", default="train-000")
    parser.add_argument("--morphologies", default="train", help="the robot set (a set name or a folder)")
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    frames = render_tasks(args.morphology, morphologies=args.morphologies)
    columns = 5
    fig, axes = plt.subplots(math.ceil(len(frames) / columns), columns, figsize=(3.2 * columns, 2.7 * math.ceil(len(frames) / columns)))
    for ax, (task, frame) in zip(axes.flat, frames):
        ax.imshow(frame)
        ax.set_title(unimal_envs.env_id(task), fontsize=10)
        ax.axis("off")
    for ax in list(axes.flat)[len(frames) :]:
        ax.axis("off")
    fig.suptitle(f"The ten UNIMAL tasks (robot {args.morphology}; `python -m unimal_envs.gallery`)", fontsize=11)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=110, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:  # a dithered 256-colour palette: ~40% of the RGBA file, no visible loss
        image.convert("RGB").quantize(256, dither=Image.Dither.FLOYDSTEINBERG).save(args.out, format="PNG", optimize=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
