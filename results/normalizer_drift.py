"""How a multi-task student's observation statistics fit its tasks, and what moving them does to a frozen student.

Training tasks only (FT, VT, Incline, Obstacle, Patrol); no novel task or novel robot is looked at.
Reads a recorded run (default ``results/cpu``: its five teachers, trained on one task each, hold
per-task statistics; its DivMorph student, distilled on the five, holds their mixture) and writes
``results/normalizer_drift.md``:

A. per-task vs mixture statistics of the absolute height column (proprioception column 2) and y
   (column 1), read from the saved ``vecnormalize.pkl`` files (no simulation);
B. drift: fixed states of each training task (the student acting with its own statistics), and the
   student's deterministic actions on them with its statistics, and with the statistics a transfer
   with learning statistics would hold after ``--drift-steps`` env steps on one *training* task
   (the student's statistics updated with that task's moments, taken from its teacher's file);
   and deterministic returns of the student with both;
C. the height above the ground under the torso (``z - arena.ground_height(x, y)``, the quantity the
   fall check already uses) on the same states: its per-task statistics, beside the absolute height's.

    python results/normalizer_drift.py                  # ~3 min on one core
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO

import sb3_divmorph  # noqa: F401
import unimal_envs  # noqa: F401
from sb3_divmorph.algos.distillation import load_normalizer
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import stage_model

TASKS = ("FT", "VT", "Incline", "Obstacle", "Patrol")
KEY = "proprioceptive"


def statistics(folder: Path):
    return load_normalizer(folder / "vecnormalize.pkl").obs_rms[KEY]


def rollout(model, normalizer, task: str, robots: list[Path], steps: int, seed: int):
    """Raw states, torso heights above the ground, and the deterministic return of each robot's episode."""
    states, relative, absolute, returns = [], [], [], []
    for i, robot in enumerate(robots):
        env = gym.make(f"Unimal-{task}-v0", morphologies=[robot], max_episode_steps=steps)
        obs, _ = env.reset(seed=seed + i)
        total, done = 0.0, False
        while not done:
            base = env.unwrapped
            x, y, z = base.robot.torso_qpos.tolist()
            relative.append(z - base.arena.ground_height(x, y))
            absolute.append(z)
            states.append(obs)
            batch = {k: v[None] for k, v in obs.items()}
            action = model.predict(normalizer.normalize_obs(batch), deterministic=True)[0][0]
            obs, reward, terminated, truncated, _ = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
        env.close()
    return states, np.array(relative), np.array(absolute), returns


def episode_returns(model, normalizer, task: str, robots: list[Path], steps: int, seed: int) -> list[float]:
    return rollout(model, normalizer, task, robots, steps, seed)[3]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default="results/cpu")
    parser.add_argument("--robots", type=int, default=3, help="first N training robots of the run")
    parser.add_argument("--steps", type=int, default=300, help="steps per episode (states and returns)")
    parser.add_argument("--drift-steps", type=int, default=60_000, help="env steps of the stand-in new task")
    parser.add_argument("--out", default="results/normalizer_drift.md")
    args = parser.parse_args()
    th.set_num_threads(1)
    start = time.time()
    run = Path(args.run)
    profile = recorded_profile(run / "run.json")
    robots = profile_robots(profile, "train")[: args.robots]
    student = PPO.load(stage_model(run / "student"), device="cpu")
    normalizer = load_normalizer(run / "student" / "vecnormalize.pkl")
    mixture = normalizer.obs_rms[KEY]
    per_task = {task: statistics(run / "teachers" / task) for task in TASKS}

    lines = [
        "# Observation statistics of a multi-task student, and what moving them does",
        "",
        f"`python results/normalizer_drift.py --run {args.run} --robots {args.robots} --steps {args.steps} "
        f"--drift-steps {args.drift_steps}`; machine: {platform.node()} ({platform.machine()}, 1 torch thread); "
        "training tasks and training robots only.",
        "",
        "## A. Per-task statistics (each teacher's) and the student's mixture",
        "",
        "Torso token; the limbs' height columns behave the same. Mixture units: (task mean - mixture mean) / mixture sd, "
        "and the task's sd / the mixture's sd (how much of the normalised range the task's own variation spans).",
        "",
        "| statistics | count | y mean | y sd | height z mean (m) | z sd (m) | z mean in mixture units | z sd / mixture z sd |",
        "|---|---|---|---|---|---|---|---|",
    ]
    mz, sz = mixture.mean[0, 2], np.sqrt(mixture.var[0, 2])
    for name, rms in [*per_task.items(), ("student (mixture)", mixture)]:
        m, s = rms.mean[0], np.sqrt(rms.var[0])
        lines.append(
            f"| {name} | {rms.count:,.0f} | {m[1]:.2f} | {s[1]:.2f} | {m[2]:.2f} | {s[2]:.3f} | {(m[2] - mz) / sz:+.2f} | {s[2] / sz:.3f} |"
        )

    # B and C: fixed states of every training task, with the student acting on its own statistics
    states, heights, base_returns = {}, {}, {}
    for task in TASKS:
        found, relative, absolute, returns = rollout(student, normalizer, task, robots, args.steps, profile.seed)
        states[task] = {k: np.stack([s[k] for s in found]) for k in found[0]}
        heights[task] = (relative, absolute)
        base_returns[task] = returns

    def actions(norm, task):
        return student.predict(norm.normalize_obs(states[task]), deterministic=True)[0]

    real = {task: states[task]["act_padding_mask"] < 0.5 for task in TASKS}
    reference = {task: actions(normalizer, task) for task in TASKS}
    lines += [
        "",
        f"## B. Drift: the student's statistics after {args.drift_steps:,} env steps of one training task",
        "",
        "A transfer whose statistics go on learning adds the new task's states to them. Stand-in new tasks: training "
        "tasks, their moments from their teachers' statistics (count = the drift steps). Action change: mean |delta a| "
        "over the real action slots of the fixed states, / mean |a|; returns: deterministic, "
        f"{args.robots} training robots x 1 episode of {args.steps} steps, with the original / drifted statistics.",
        "",
    ]
    header = "| statistics learnt on | new z mean / sd (m) | " + " | ".join(f"{t}: action change, return" for t in TASKS) + " |"
    lines += [header, "|---" * (2 + len(TASKS)) + "|"]
    height = np.zeros(mixture.mean.shape[-1], bool)
    height[2] = True
    for source, columns in (
        ("FT", None),
        ("Patrol", None),
        ("Incline", None),
        ("FT, height column only", height),
        ("FT, every column but height", ~height),
    ):
        drifted = load_normalizer(run / "student" / "vecnormalize.pkl")  # a fresh copy
        moments = per_task[source.split(",")[0]]
        learnt = drifted.obs_rms[KEY]
        before_mean, before_var = learnt.mean.copy(), learnt.var.copy()
        learnt.update_from_moments(moments.mean, moments.var, float(args.drift_steps))
        if columns is not None:  # only these columns drift
            learnt.mean[:, ~columns], learnt.var[:, ~columns] = before_mean[:, ~columns], before_var[:, ~columns]
        cells = []
        for task in TASKS:
            change = np.abs(actions(drifted, task) - reference[task])[real[task]].mean() / np.abs(reference[task][real[task]]).mean()
            after = episode_returns(student, drifted, task, robots, args.steps, profile.seed)
            cells.append(f"{change:.2f}, {np.mean(base_returns[task]):.1f} -> {np.mean(after):.1f}")
        new = drifted.obs_rms[KEY]
        lines.append(f"| {source} | {new.mean[0, 2]:.2f} / {np.sqrt(new.var[0, 2]):.2f} | " + " | ".join(cells) + " |")

    lines += [
        "",
        "## C. Height above the ground under the torso vs absolute height, per task",
        "",
        "On the states of B (the student acting; the fall check already computes this height).",
        "",
        "| task | absolute z mean (m) | absolute z sd | above-ground mean (m) | above-ground sd |",
        "|---|---|---|---|---|",
    ]
    everything = {"relative": [], "absolute": []}
    for task in TASKS:
        relative, absolute = heights[task]
        everything["relative"].append(relative)
        everything["absolute"].append(absolute)
        lines.append(f"| {task} | {absolute.mean():.2f} | {absolute.std():.3f} | {relative.mean():.3f} | {relative.std():.3f} |")
    rel, ab = np.concatenate(everything["relative"]), np.concatenate(everything["absolute"])
    lines.append(f"| all five (pooled) | {ab.mean():.2f} | {ab.std():.3f} | {rel.mean():.3f} | {rel.std():.3f} |")
    flat_sd = np.sqrt(per_task["FT"].var[0, 2])
    lines += [
        "",
        "## Decision",
        "",
        "1. **Transfer keeps the statistics it inherits** (always, since divmorph 0.2; "
        "reward statistics start afresh and learn). B: letting them learn for one task's worth of steps moves the "
        "student's actions by a large fraction of their size on every training task and takes most of its return "
        "with it, with no weight changed.",
        "   The height column alone accounts for it (the rows of B that drift one group of columns): the mixture "
        "squeezes a flat task's height variation into a few hundredths of a normalised unit (A), so the student "
        "reads heights through large weights, and a shift of the mixture's mean by a few tenths of a metre reads as "
        "a different posture.",
        "2. **Multi-task students keep one set of statistics, not per-task ones.** Per-task statistics fit the "
        "training tasks (A) but a novel task has none: the student would meet it with statistics of another task, "
        "or have to learn them, which is the drift of B.",
        f"3. **Height relative to the ground is the better input for a multi-task student**: pooled over the five "
        f"tasks, the above-ground height has sd {rel.std():.2f} m around {rel.mean():.2f} m, close to every task's own "
        f"(C), while the world height's mixture (sd {np.sqrt(mixture.var[0, 2]):.1f} m, A) squeezes FT's own variation "
        f"(sd {flat_sd:.2f} m) into {flat_sd / np.sqrt(mixture.var[0, 2]):.3f} of a normalised unit and puts Incline "
        f"{abs((per_task['Incline'].mean[0, 2] - mz) / sz):.1f} sd away from the rest. It is the contract option "
        '`gym.make(..., height_reference="ground")`; MetaMorph\'s world height stays the default (and the shipped '
        "models were trained with it).",
        "",
    ]
    lines += [f"Wall time: {time.time() - start:.0f} s.", ""]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
