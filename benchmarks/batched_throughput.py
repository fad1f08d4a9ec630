"""Env steps/s of the batched backend (MuJoCo Warp) against the single C env, side by side.

In one run on one machine, for FT and VT on the first R robots of a set:

* **single**: one ``gym.make("Unimal-<task>-v0")`` env per core, stepped with random actions over
  the same robots (one world at a time, the C MuJoCo path; steps/s of one core);
* **batched (cpu)**: :func:`unimal_envs.batched.make_batched_env` on CPU Warp, ``W`` worlds per
  robot, stepped through its torch interface (observations, rewards and resets included);
* **batched (cuda)**: the same on the GPU, when a CUDA device is present.

Then end-to-end PPO steps/s (rollout + update, SB3's PPO with the MetaMorph policy at the
``small`` and ``paper`` presets) on the single backend (``n_envs`` single envs) and on the batched
one. Warm-up (kernel compilation, CUDA graph capture, the first rollout) is excluded from every
timing and reported separately.

Usage::

    python benchmarks/batched_throughput.py [--robots 10 100] [--worlds 1 8 32] [--devices cpu cuda]

Writes ``results/batched_throughput.md``. Targets on one H100: >= 200k env steps/s on FT across
100 robots, >= 100k on VT, PPO end-to-end (small model) >= 30k steps/s.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from datetime import date
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import unimal_envs
from unimal_envs import contract as C
from unimal_envs.morphology.loader import morphology_files

RESULTS = Path(__file__).resolve().parent.parent / "results" / "batched_throughput.md"


def single_steps_per_second(task: str, files: list[Path], seconds: float) -> float:
    """Random-action env steps/s of one single env cycling over ``files`` (resets excluded)."""
    env = gym.make(unimal_envs.env_id(task), morphologies=files)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    steps, busy = 0, 0.0
    while busy < seconds:
        actions = rng.uniform(-1, 1, (200, C.ACTION_DIM)).astype(np.float32)
        start = time.perf_counter()
        for action in actions:
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                busy += time.perf_counter() - start
                env.reset()
                start = time.perf_counter()
            steps += 1
        busy += time.perf_counter() - start
    env.close()
    return steps / busy


def batched_steps_per_second(env, seconds: float) -> tuple[float, float]:
    """(env steps/s through the torch interface, seconds of warm-up: 3 steps incl. compilation)."""
    n = env.num_envs
    generator = torch.Generator(device=env.torch_device).manual_seed(0)
    random = lambda: torch.rand((n, C.ACTION_DIM), generator=generator, device=env.torch_device) * 2 - 1  # noqa: E731
    start = time.perf_counter()
    env.reset_tensors()
    for _ in range(3):
        env.step_tensors(random())
    _synchronize(env)
    warmup = time.perf_counter() - start
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for _ in range(10):
            env.step_tensors(random())
        steps += 10
        _synchronize(env)
    return n * steps / (time.perf_counter() - start), warmup


def _synchronize(env) -> None:
    if env.torch_device.type == "cuda":
        torch.cuda.synchronize(env.torch_device)


def ppo_steps_per_second(make_env, preset: str, device: str, n_steps: int, rollouts: int) -> tuple[float, int]:
    """End-to-end PPO samples/s (rollouts + updates) after one warm-up rollout; and the rollout size."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    import sb3_divmorph  # noqa: F401  (policy aliases)

    venv = VecNormalize(make_env(), norm_obs_keys=["proprioceptive", "hfield"], norm_reward=True)
    rollout = venv.num_envs * n_steps
    model = PPO("MetaMorphPolicy", venv, n_steps=n_steps, batch_size=min(rollout, 4096), n_epochs=2,
                policy_kwargs={"preset": preset}, device=device, seed=0)
    model.learn(rollout)
    start = time.perf_counter()
    model.learn(rollouts * rollout, reset_num_timesteps=False)
    return rollouts * rollout / (time.perf_counter() - start), rollout


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--morphologies", default="train", help="robot set (default: the shipped train set)")
    parser.add_argument("--tasks", nargs="*", default=["FT", "VT"])
    parser.add_argument("--robots", nargs="*", type=int, default=[10, 100])
    parser.add_argument("--worlds", nargs="*", type=int, default=[1, 8, 32], help="worlds per robot")
    parser.add_argument("--devices", nargs="*", default=["cpu", "cuda"], help="batched devices (cuda skipped without one)")
    parser.add_argument("--max-worlds-cpu", type=int, default=1024, help="skip CPU Warp batches larger than this")
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per measurement")
    parser.add_argument("--ppo-robots", type=int, default=10)
    parser.add_argument("--ppo-worlds", nargs="*", type=int, default=[8], help="worlds per robot of the PPO rows (cpu, cuda)")
    parser.add_argument("--ppo-presets", nargs="*", default=["small", "paper"])
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    from unimal_envs.batched import make_batched_env

    torch.set_num_threads(1)
    devices = [d for d in args.devices if d != "cuda" or torch.cuda.is_available()]
    skipped = [d for d in args.devices if d not in devices]
    env_rows: list[tuple] = []
    for task in args.tasks:
        for robots in args.robots:
            files = morphology_files(args.morphologies)[:robots]
            single = single_steps_per_second(task, files, args.seconds)
            env_rows.append((task, len(files), "single (1 core)", 1, 1, single, 0.0, "-"))
            print(f"{task} {len(files)} robots single: {single:.0f} steps/s", flush=True)
            for device in devices:
                for worlds in args.worlds:
                    if device == "cpu" and worlds * len(files) > args.max_worlds_cpu:
                        continue
                    env = make_batched_env(task, morphologies=files, worlds_per_robot=worlds, device=device, seed=0)
                    rate, warmup = batched_steps_per_second(env, args.seconds)
                    overflow = ", ".join(f"{kind} {n}" for kind, n in env.overflow_report().items()) or "none"
                    env.close()
                    env_rows.append((task, len(files), f"batched ({device})", worlds, env.num_envs, rate, warmup, overflow))
                    print(f"{task} {len(files)} robots batched {device} W={worlds}: {rate:.0f} steps/s "
                          f"({rate / single:.1f}x single; warm-up {warmup:.1f} s)", flush=True)

    ppo_rows: list[tuple] = []
    files = morphology_files(args.morphologies)[: args.ppo_robots]
    from sb3_divmorph.pipeline.runs import make_vec_env

    for preset in args.ppo_presets:
        single_envs = 8
        rate, rollout = ppo_steps_per_second(lambda: make_vec_env("Unimal-FT-v0", single_envs, 0, 1000, morphologies=files),
                                             preset, "cpu", 64, 2)
        ppo_rows.append((preset, f"single x {single_envs} (cpu)", single_envs, rollout, rate))
        print(f"PPO {preset} single x{single_envs}: {rate:.0f} steps/s", flush=True)
        for device in devices:
            for worlds in args.ppo_worlds:
                make = lambda: make_vec_env("Unimal-FT-v0", 0, 0, 1000, "batched", worlds, device, morphologies=files)  # noqa: E731
                rate, rollout = ppo_steps_per_second(make, preset, device, 16, 2)
                ppo_rows.append((preset, f"batched ({device}), {worlds} worlds/robot", len(files) * worlds, rollout, rate))
                print(f"PPO {preset} batched {device} W={worlds}: {rate:.0f} steps/s", flush=True)

    command = "python benchmarks/batched_throughput.py " + " ".join(argv if argv is not None else sys.argv[1:])
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    lines = [
        "# Batched backend (MuJoCo Warp) throughput vs. the single C env",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {platform.processor() or platform.machine()}, {platform.system()}, {torch.get_num_threads()} torch thread(s), "
        f"GPU: {gpu}; Python {platform.python_version()}, mujoco-warp {_version('mujoco-warp')}, warp-lang {_version('warp-lang')}, "
        f"torch {torch.__version__}; date {date.today()}  ",
        f"Robots: the first R of `{args.morphologies}`; random actions in [-1, 1]; {args.seconds:.0f} s per measurement; "
        "batched steps go through the torch interface (observations, rewards, terminations and auto-resets on the "
        "device included); the single env's resets are not timed.",
    ]
    if skipped:
        lines.append(f"No {', '.join(skipped)} device on this machine: those rows are missing; run the same command on a GPU machine.")
    lines += [
        "",
        "## Env steps/s",
        "",
        "Overflow: world-steps in which MuJoCo Warp dropped contacts or constraint rows for lack of room "
        "(`BatchedUnimalEnv.overflow_report()`, by kind); it should read `none`.",
        "",
        "| task | robots | backend | worlds/robot | envs | env steps/s | vs single | warm-up (s) | overflow |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    singles = {(t, r): rate for t, r, backend, _, _, rate, _, _ in env_rows if backend.startswith("single")}
    for task, robots, backend, worlds, envs, rate, warmup, overflow in env_rows:
        lines.append(f"| {task} | {robots} | {backend} | {worlds} | {envs} | {rate:,.0f} | {rate / singles[task, robots]:.2f}x "
                     f"| {warmup:.1f} | {overflow} |")
    lines += [
        "",
        f"## PPO end to end (FT, {len(files)} robots, MetaMorph policy)",
        "",
        "Samples/s of `PPO.learn` over two rollouts (collection + 2 epochs of updates, batch <= 4096) after one warm-up rollout; "
        "single rollouts are 64 steps x 8 envs, batched rollouts 16 steps x all worlds.",
        "",
        "| preset | backend | envs | rollout | PPO steps/s |",
        "|---|---|---|---|---|",
    ]
    for preset, backend, envs, rollout, rate in ppo_rows:
        lines.append(f"| {preset} | {backend} | {envs} | {rollout} | {rate:,.0f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


def _version(name: str) -> str:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    main()
