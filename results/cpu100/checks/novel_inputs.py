"""Do a run's models see novel robots' inputs inside the range they learnt on? A control for zero-shot.

    python results/cpu100/checks/novel_inputs.py --run results/cpu100 --out results/cpu100/checks/novel-inputs.md

When a model's return collapses on novel robots, one cause could be inputs the model never saw: the
teacher's observation statistics, fitted on the training robots, could put novel robots' observations
far outside the normalised range. This script rolls out each teacher (deterministic, its own
statistics) on the transfer curves' robots of both sets (``transfer.eval_robots``, spread over each
set) and compares, per observation key, the normalised inputs of the novel robots with those of the
training robots: the share of entries beyond |z| > 5 and the mean |z|, plus the episode lengths.
Similar ranges mean the collapse is the policy's response to new bodies, not inputs out of range.
"""

from __future__ import annotations

import argparse
import pickle
import platform
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import PPO

from divmorph.pipeline.curves import robot_venv
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.envs import task_env_name
from divmorph.pipeline.robots import trained_env_kwargs, transfer_eval_robots
from divmorph.pipeline.training import stage_model, stage_normalizer

#: |z| beyond which a normalised input counts as far out (VecNormalize clips at 10).
FAR = 5.0


def input_ranges(folder: Path, task: str, robots: list[Path], steps: int, seed: int = 0) -> dict[str, tuple[float, float]]:
    """``{key: (share of |z| > FAR, mean |z|)}`` of the model's normalised inputs over ``steps`` deterministic
    steps on ``robots`` (one env per robot; a fallen robot restarts), and ``"episode length"``: (mean length, episodes)."""
    with open(stage_normalizer(folder), "rb") as f:
        normalizer = pickle.load(f)
    model = PPO.load(stage_model(folder), device="cpu")
    venv = robot_venv(task_env_name(task), robots, 1000, seed, **trained_env_kwargs(folder))
    obs = venv.reset()
    seen: dict[str, list[np.ndarray]] = {}
    lengths: list[int] = []
    for _ in range(steps):
        z = normalizer.normalize_obs(obs)
        for key, value in z.items():
            seen.setdefault(key, []).append(np.abs(np.asarray(value, dtype=np.float64)).reshape(len(robots), -1))
        actions, _ = model.predict(z, deterministic=True)
        obs, _, dones, infos = venv.step(actions)
        lengths += [int(infos[i]["episode"]["l"]) for i in np.flatnonzero(dones)]
    venv.close()
    ranges = {key: (float(np.mean(np.concatenate(v) > FAR)), float(np.mean(np.concatenate(v)))) for key, v in seen.items()}
    ranges["episode length"] = (float(np.mean(lengths)) if lengths else float(steps), float(len(lengths)))
    return ranges


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a recorded run folder (its teachers/ are rolled out)")
    parser.add_argument("--out", type=Path, required=True, help="the markdown report to write")
    parser.add_argument("--steps", type=int, default=300, help="steps per robot and task (default 300)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    profile = recorded_profile(args.run / "run.json")
    start = time.time()
    lines = [
        "# Novel robots' inputs against the training robots' (a control for zero-shot)",
        "",
        f"`python results/cpu100/checks/novel_inputs.py --run {args.run} --out {args.out}` -- each teacher, deterministic, with its own "
        f"observation statistics, {args.steps} steps on each of the transfer curves' robots ({len(transfer_eval_robots(profile, 'train'))} "
        f"training and {len(transfer_eval_robots(profile, 'novel'))} novel robots, spread over each set); per observation key the "
        f"share of normalised entries with |z| > {FAR:g} and the mean |z| (keys the task does not use are 0).",
        "",
        "| teacher | key | training robots: share of abs(z) > 5, mean abs(z) | novel robots: share of abs(z) > 5, mean abs(z) |",
        "|---|---|---|---|",
    ]
    for task in profile.teachers.tasks:
        folder = args.run / "teachers" / task
        found = {split: input_ranges(folder, task, transfer_eval_robots(profile, split), args.steps) for split in ("train", "novel")}
        for key in found["train"]:
            (a, b), (c, d) = found["train"][key], found["novel"][key]
            if key == "episode length":
                lines.append(
                    f"| {task} | falls in the first {args.steps} steps (episodes ended; their mean length) | {b:.0f} ({a:.0f}) | {d:.0f} ({c:.0f}) |"
                )
            elif key != "task_index" and (b or d):  # (an id, not a feature; unused keys are 0)
                lines.append(f"| {task} | {key} | {a:.4f}, {b:.2f} | {c:.4f}, {d:.2f} |")
        print(f"[novel_inputs] {task} done ({time.time() - start:.0f} s)")
    lines += [
        "",
        f"Written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.machine()}, torch {torch.__version__}, "
        f"1 thread; {time.time() - start:.0f} s.",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
