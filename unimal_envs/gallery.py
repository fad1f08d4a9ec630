"""Render one frame of every task into a picture (``results/tasks.png``).

Usage: ``python -m unimal_envs.gallery [--out results/tasks.png] [--morphology train-000]``
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import gymnasium as gym
import numpy as np

import unimal_envs
from unimal_envs.tasks import TASKS

# Where to stand and look from, per task, so that the arena's features are in view.
_VIEWS = {
    "FT": (6.0, (160.0, -20.0), 0),
    "VT": (9.0, (200.0, -22.0), 40),
    "Incline": (8.0, (110.0, -12.0), 0),
    "Obstacle": (10.0, (200.0, -28.0), 0),
    "Patrol": (10.0, (100.0, -25.0), 0),
    "Exploration": (14.0, (135.0, -35.0), 0),
    "Escape": (16.0, (200.0, -18.0), 0),
    "PointNav": (12.0, (160.0, -30.0), 0),
    "PushBoxIncline": (5.0, (150.0, -20.0), 0),
    "ManipulateBox": (9.0, (200.0, -30.0), 0),
}


def render_tasks(morphology: str, width: int = 400, height: int = 300, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """One frame per task, with a camera placed to show the task's arena and props."""
    files = [p for p in unimal_envs.morphology.morphology_files("train") if p.stem == morphology]
    frames = []
    for task in TASKS:
        env = gym.make(unimal_envs.env_id(task), morphologies=files, render_mode="rgb_array", width=width, height=height)
        env.reset(seed=seed)
        distance, angles, walk = _VIEWS[task]
        base = env.unwrapped
        base.camera_distance, base.camera_angles = distance, angles
        if walk:  # VT: move the robot onto the terrain segments so they are in view
            base.data.qpos[0] += walk
            base.data.qpos[2] += base.task.arena.ground_height(float(base.data.qpos[0]), 0.0)
            env.step(np.zeros(env.action_space.shape, np.float32))
        frames.append((task, env.render()))
        env.close()
    return frames


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Render one frame of every UNIMAL task into a grid picture.")
    parser.add_argument("--out", type=Path, default=Path("results/tasks.png"))
    parser.add_argument("--morphology", default="train-000")
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = render_tasks(args.morphology)
    columns = 5
    fig, axes = plt.subplots(math.ceil(len(frames) / columns), columns, figsize=(3.2 * columns, 2.7 * math.ceil(len(frames) / columns)))
    for ax, (task, frame) in zip(axes.flat, frames):
        ax.imshow(frame)
        ax.set_title(f"Unimal-{task}-v0", fontsize=10)
        ax.axis("off")
    for ax in list(axes.flat)[len(frames):]:
        ax.axis("off")
    fig.suptitle(f"The ten UNIMAL tasks (robot {args.morphology}; `python -m unimal_envs.gallery`)", fontsize=11)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
