"""A tour of the UNIMAL envs: open-loop gaits across several morphologies.

For each of ``--count`` robots of a morphology set, this rolls out full ``Unimal-FT-v0`` episodes
with (a) uniform random actions and (b) the best of ``--gaits`` random sinusoidal gaits (every
hinge follows ``sin(2 pi f t + phase)``, phases drawn at random: a scripted policy found by
random search, no learning). It prints a per-morphology table, and writes under ``--out``:

* ``summary.md`` — the same table, with the command and seed;
* ``robots.png`` — a picture of every robot, each panel titled with its name, limbs and dof;
* ``gaits.mp4`` — a short video of each robot walking with its best gait.

Usage: ``python -m unimal_envs.demo [--morphologies train] [--count 6] [--out runs/demo]``
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, cast

import gymnasium as gym
import numpy as np

import unimal_envs  # noqa: F401  (registers the Unimal-* environments with gymnasium)
from unimal_envs import contract as C
from unimal_envs.rendering import record_episode, write_video

if TYPE_CHECKING:
    from unimal_envs.env import UnimalEnv


class SineGait:
    """Open-loop gait: real hinge slot ``i`` outputs ``amplitude * sin(2 pi f t + phase_i)``.

    :param phases: (24,) phase per action slot.
    :param frequency: gait frequency in Hz.
    :param amplitude: action amplitude in [0, 1].
    """

    def __init__(self, phases: np.ndarray, frequency: float = 1.5, amplitude: float = 1.0):
        self.phases, self.frequency, self.amplitude = phases, frequency, amplitude
        self.t = 0

    def __call__(self, obs: dict) -> np.ndarray:
        time_s = self.t * 0.02
        self.t += 1
        return (self.amplitude * np.sin(2 * math.pi * self.frequency * time_s + self.phases)).astype(np.float32)


def run_episode(env: gym.Env, policy, seed: int, morphology: str) -> tuple[float, float, int, bool]:
    """Return, forward distance, length and whether the robot fell, for one episode."""
    obs, _ = env.reset(seed=seed, options={"morphology": morphology})
    unimal = cast("UnimalEnv", env.unwrapped)
    start_x = unimal.robot.torso_x
    total, steps, fell = 0.0, 0, False
    while True:
        action = env.action_space.sample() if policy is None else policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        if terminated or truncated:
            fell = info.get("termination") == "fall"
            break
    return total, unimal.robot.torso_x - start_x, steps, fell


def robot_figure(pictures: list[np.ndarray], labels: list[str], title: str, columns: int = 3):
    """A grid of robot pictures, each panel titled with its label (robot name, limbs, dof).

    :param pictures: equally sized RGB images, one per robot.
    :param labels: one panel title per picture.
    :param title: the figure's title (task, robot set, seed).
    :param columns: panels per row.
    :returns: the matplotlib figure (``fig.savefig(path)`` writes it).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(pictures) != len(labels) or not pictures:
        raise ValueError(f"need one label per picture, got {len(pictures)} pictures and {len(labels)} labels")
    columns = min(columns, len(pictures))
    rows = math.ceil(len(pictures) / columns)
    h, w, _ = pictures[0].shape
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows * h / w + 0.6), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, picture, label in zip(axes.flat, pictures, labels):
        ax.imshow(picture)
        ax.set_title(label, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Open-loop gaits across UNIMAL morphologies (Unimal-FT-v0).")
    parser.add_argument("--morphologies", default="train", help="set name, directory or file (default: train)")
    parser.add_argument("--count", type=int, default=6, help="number of robots")
    parser.add_argument("--gaits", type=int, default=6, help="random sine gaits tried per robot")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/demo"))
    parser.add_argument("--video-steps", type=int, default=150, help="video length per robot, in steps")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)

    from rich.console import Console
    from rich.table import Table
    from tqdm import tqdm

    console = Console()
    start = time.time()
    env = gym.make("Unimal-FT-v0", morphologies=args.morphologies)
    rng = np.random.default_rng(args.seed)
    every = cast("UnimalEnv", env.unwrapped).morphologies
    robots = [every[i] for i in sorted(rng.choice(len(every), args.count, replace=False))]
    env.action_space.seed(args.seed)

    rows, best_gaits = [], {}
    for robot in tqdm(robots, desc="robots", unit="robot", disable=args.no_progress):
        random_return, random_dist, random_len, random_fell = run_episode(env, None, args.seed, robot.name)
        best = None
        for _ in range(args.gaits):
            gait = SineGait(rng.uniform(0, 2 * math.pi, C.ACTION_DIM), rng.uniform(0.8, 2.5), rng.uniform(0.2, 1.0))
            result = run_episode(env, gait, args.seed, robot.name)
            if best is None or result[0] > best[0][0]:
                best = (result, gait)
        assert best is not None, "--gaits must be at least 1"
        best_gaits[robot.name] = best[1]
        (gait_return, gait_dist, gait_len, gait_fell) = best[0]
        rows.append((robot, random_return, random_dist, random_len, random_fell, gait_return, gait_dist, gait_len, gait_fell))

    table = Table(
        title=f"Unimal-FT-v0, {len(robots)} robots of '{args.morphologies}' (seed {args.seed}): random actions vs best of {args.gaits} sine gaits"
    )
    headers = ["morphology", "limbs", "dof", "random return", "random dx (m)", "random steps", "gait return", "gait dx (m)", "gait steps"]
    for header in headers:
        table.add_column(header, justify="right", no_wrap=header == "morphology")
    markdown = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for robot, rr, rd, rl, rf, gr, gd, gl, gf in rows:
        cells = [
            robot.name,
            str(robot.num_limbs),
            str(robot.dof),
            f"{rr:.1f}",
            f"{rd:+.2f}",
            f"{rl}{' (fell)' if rf else ''}",
            f"{gr:.1f}",
            f"{gd:+.2f}",
            f"{gl}{' (fell)' if gf else ''}",
        ]
        table.add_row(*cells)
        markdown.append("| " + " | ".join(cells) + " |")
    console.print(table)

    args.out.mkdir(parents=True, exist_ok=True)
    render_env = gym.make("Unimal-FT-v0", morphologies=[r.path for r in robots], render_mode="rgb_array", width=320, height=240)
    pictures, labels, frames = [], [], []
    for robot in tqdm(robots, desc="rendering", unit="robot", disable=args.no_progress):
        render_env.reset(seed=args.seed, options={"morphology": robot.name})
        pictures.append(cast(np.ndarray, render_env.render()))  # an rgb_array env's frame
        labels.append(f"{robot.name}: {robot.num_limbs} limbs, {robot.dof} dof")
        gait = best_gaits[robot.name]
        gait.t = 0
        clip, _ = record_episode(render_env, gait, steps=args.video_steps, seed=args.seed, options={"morphology": robot.name})
        frames.extend(clip)
    render_env.close()

    import matplotlib.pyplot as plt

    figure = robot_figure(
        pictures, labels, f"{len(robots)} robots of '{args.morphologies}' (seed {args.seed}) at their Unimal-FT-v0 start pose"
    )
    figure.savefig(args.out / "robots.png", dpi=100)
    plt.close(figure)
    write_video(frames, args.out / "gaits.mp4", fps=50)
    command = "python -m unimal_envs.demo " + " ".join(argv if argv is not None else sys.argv[1:])
    summary = [
        "# UNIMAL env demo",
        "",
        f"Command: `{command.strip()}`; seed {args.seed}; {time.time() - start:.0f} s.",
        "Episodes of up to 1000 steps (20 s) on Unimal-FT-v0; return = sum of forward speed (about 50 x distance).",
        "",
        *markdown,
        "",
        "Files: `robots.png` (the robots), `gaits.mp4` (best gait of each robot).",
    ]
    (args.out / "summary.md").write_text("\n".join(summary) + "\n")
    console.print(f"wrote {args.out / 'summary.md'}, {args.out / 'robots.png'}, {args.out / 'gaits.mp4'} in {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
