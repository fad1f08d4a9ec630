"""Env steps/s of the UNIMAL envs against the physics limit of the same compiled models.

For each of N morphologies, the env is stepped with pre-sampled random actions and, on the very
same compiled model, ``mj_step(nstep=4)`` alone is timed (the physics limit: what an env step
would cost with zero Python overhead). Blocks alternate between the two and the median over
blocks is kept, so both are measured side by side under the same machine load. Resets are not
timed in the step measurement; reset time per task is reported separately.

Usage::

    python benchmarks/env_throughput.py [--morphologies train] [--count 20] [--steps 2000]

Writes ``results/env_throughput.md``. Target: ratio >= 0.7.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from datetime import date
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np

import unimal_envs
from unimal_envs.morphology.loader import morphology_files
from unimal_envs.tasks import TASKS

RESULTS = Path(__file__).resolve().parent.parent / "results" / "env_throughput.md"


class _TimedPhysics:
    """Stands in for the ``mujoco`` module inside :mod:`unimal_envs.env` and times its ``mj_step``
    calls, so the physics of the env's own trajectory can be told from the rest of a step."""

    def __init__(self):
        self.seconds = 0.0

    def __getattr__(self, name: str):
        return getattr(mujoco, name)

    def mj_step(self, *args, **kwargs) -> None:
        start = time.perf_counter()
        mujoco.mj_step(*args, **kwargs)
        self.seconds += time.perf_counter() - start


def time_env(env: gym.Env, actions: np.ndarray) -> float:
    """Seconds per env step (time spent in resets after a termination is subtracted)."""
    in_resets = 0.0
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            reset_start = time.perf_counter()
            env.reset()
            in_resets += time.perf_counter() - reset_start
    return (time.perf_counter() - start - in_resets) / len(actions)


def time_overhead(env: gym.Env, actions: np.ndarray) -> tuple[float, float]:
    """(seconds per env step, seconds of ``mj_step`` inside those steps), on the env's own trajectory.

    The separate physics run of :func:`time_physics` replays the controls from the spawn state, so
    where the env ends episodes early (a robot sliding off the incline's lower edge is a fall for
    the env, but keeps falling cheaply in a bare ``mj_step`` loop) the two trajectories differ; the
    time per step minus its own ``mj_step`` time is the env's overhead (its Python, the
    kinematics and sensors it evaluates once per step) on the very states it simulated."""
    import unimal_envs.env as env_module

    timed = _TimedPhysics()
    env_module.mujoco = timed
    try:
        per_step = time_env(env, actions)
    finally:
        env_module.mujoco = mujoco
    return per_step, timed.seconds / len(actions)


def time_physics(model: mujoco.MjModel, data: mujoco.MjData, ctrls: np.ndarray) -> float:
    """Seconds per ``mj_step(nstep=4)`` with the same control sequence."""
    mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)
    start = time.perf_counter()
    for ctrl in ctrls:
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data, nstep=4)
    return (time.perf_counter() - start) / len(ctrls)


def measure_task(task: str, files: list[Path], steps: int, blocks: int, wrapped: bool) -> dict:
    rows = []
    for i, path in enumerate(files):
        env = gym.make(unimal_envs.env_id(task), morphologies=[path]) if wrapped else unimal_envs.UnimalEnv(task, [path])
        env.reset(seed=i)
        base = env.unwrapped
        rng = np.random.default_rng(i)
        actions = rng.uniform(-1, 1, size=(steps, unimal_envs.contract.ACTION_DIM)).astype(np.float32)
        ctrls = actions[:, base.robot._ctrl_slots]
        env_times, phys_times, overheads, inside = [], [], [], []
        for _ in range(blocks):
            env_times.append(time_env(env, actions))
            phys_times.append(time_physics(base.model, mujoco.MjData(base.model), ctrls))
            step_s, physics_s = time_overhead(env, actions)
            overheads.append(step_s - physics_s)
            inside.append(physics_s / step_s)
        reset_times = []
        for k in range(10):
            start = time.perf_counter()
            env.reset(seed=1000 + k)
            reset_times.append(time.perf_counter() - start)
        env_s, phys_s = statistics.median(env_times), statistics.median(phys_times)
        rows.append(
            {
                "name": path.stem,
                "env": 1 / env_s,
                "physics": 1 / phys_s,
                "ratio": phys_s / env_s,
                "reset_ms": 1000 * statistics.median(reset_times),
                "overhead_us": 1e6 * statistics.median(overheads),
                "own_ratio": statistics.median(inside),
            }
        )
        env.close()
    # Worst case: every reset draws a robot whose world is not cached, so it is compiled anew.
    cold = gym.make(unimal_envs.env_id(task), morphologies=files, world_cache_size=1)
    cold.reset(seed=0)
    cold_times = []
    for k in range(len(files)):
        start = time.perf_counter()
        cold.reset(seed=k, options={"morphology": (k + 1) % len(files)})
        cold_times.append(time.perf_counter() - start)
    cold.close()
    return {
        "task": task,
        "cold_reset_ms": 1000 * statistics.median(cold_times),
        "cold_reset_max_ms": 1000 * max(cold_times),
        "rows": rows,
        "env": statistics.mean(r["env"] for r in rows),
        "physics": statistics.mean(r["physics"] for r in rows),
        "ratio": statistics.median(r["ratio"] for r in rows),
        "min_ratio": min(r["ratio"] for r in rows),
        "reset_ms": statistics.median(r["reset_ms"] for r in rows),
        "overhead_us": statistics.median(r["overhead_us"] for r in rows),
        "own_ratio": statistics.median(r["own_ratio"] for r in rows),
        "min_own_ratio": min(r["own_ratio"] for r in rows),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--morphologies", default="train", help="set name or directory (default: shipped train set)")
    parser.add_argument("--count", type=int, default=20, help="number of morphologies")
    parser.add_argument("--steps", type=int, default=2000, help="steps per timing block")
    parser.add_argument("--blocks", type=int, default=3, help="alternating env/physics blocks per morphology")
    parser.add_argument("--tasks", nargs="*", default=sorted(TASKS), help="tasks to measure")
    parser.add_argument("--unwrapped", action="store_true", help="time UnimalEnv without gym.make's wrappers")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    files = morphology_files(args.morphologies)[: args.count]
    results = []
    for task in args.tasks:
        result = measure_task(task, files, args.steps, args.blocks, wrapped=not args.unwrapped)
        results.append(result)
        print(
            f"{task:<16} env {result['env']:8.0f} steps/s   physics {result['physics']:8.0f} steps/s   "
            f"ratio {result['ratio']:.2f} (min {result['min_ratio']:.2f})   own trajectory {result['own_ratio']:.2f} "
            f"(min {result['min_own_ratio']:.2f}), {result['overhead_us']:.1f} us/step besides mj_step   "
            f"reset {result['reset_ms']:.1f} ms, "
            f"with a new robot {result['cold_reset_ms']:.1f} ms (max {result['cold_reset_max_ms']:.1f})"
        )

    command = "python benchmarks/env_throughput.py " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "# Env throughput vs. the physics limit",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {platform.processor() or platform.machine()}, {platform.system()}, Python {platform.python_version()}, "
        f"mujoco {mujoco.__version__}, one process (one core); date {date.today()}  ",
        f"Morphologies: {len(files)} from `{args.morphologies}`; {args.steps} random-action steps x {args.blocks} "
        f"alternating blocks; env {'unwrapped' if args.unwrapped else 'from gym.make (TimeLimit, OrderEnforcing, PassiveEnvChecker)'}.",
        "",
        "Ratio = env steps/s / physics steps/s, where physics = `mj_step(nstep=4)` on the same compiled model "
        "with the same controls (median over morphologies; the world's sensors are off while `mj_step` runs, so the "
        "proprioception sensors the env reads once per step count as env time). Target: ratio >= 0.7; reset < 50 ms. "
        "Reset = a new episode of a cached world (terrain and props re-randomised in place); "
        "reset with a new robot = the world is compiled first (cache miss).",
        "",
        "Own trajectory = the share of an env step spent in its own `mj_step` call, and us/step = the rest of the "
        "step (Python, and the kinematics and sensors evaluated once per step), timed inside the env's steps: the "
        "separate physics run replays the controls from the spawn state, so where the env ends episodes early "
        "(a robot sliding off the incline's lower edge falls for the env but keeps falling, cheaply, in a bare "
        "`mj_step` loop) the first ratio compares different trajectories.",
        "",
        "| task | env steps/s | physics steps/s | ratio (median) | ratio (min) | own trajectory (median / min) | us/step besides mj_step | reset (ms, median) | reset with a new robot (ms, median / max) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['task']} | {r['env']:.0f} | {r['physics']:.0f} | {r['ratio']:.2f} | {r['min_ratio']:.2f} | "
            f"{r['own_ratio']:.2f} / {r['min_own_ratio']:.2f} | {r['overhead_us']:.1f} | "
            f"{r['reset_ms']:.1f} | {r['cold_reset_ms']:.1f} / {r['cold_reset_max_ms']:.1f} |"
        )
    lines += [
        "",
        "Per morphology:",
        "",
        "| task | morphology | env steps/s | physics steps/s | ratio | reset (ms) |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        for row in r["rows"]:
            lines.append(
                f"| {r['task']} | {row['name']} | {row['env']:.0f} | {row['physics']:.0f} | {row['ratio']:.2f} | {row['reset_ms']:.1f} |"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
