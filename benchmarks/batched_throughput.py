"""Env steps/s of the batched backend (MuJoCo Warp) against the single C env, side by side.

In one run on one machine, for FT and VT on the first R robots of a set:

* **single**: one ``gym.make("Unimal-<task>-v0")`` env per core, stepped with random actions over
  the same robots (one world at a time, the C MuJoCo path; steps/s of one core);
* **batched (cpu)**: :func:`unimal_envs.batched.make_batched_env` on CPU Warp, ``W`` worlds per
  robot, stepped through its torch interface (observations, rewards and resets included);
* **batched (cuda)**: the same on the GPU, when a CUDA device is present.

Then end-to-end PPO steps/s (rollout + update, with the MetaMorph policy at the ``small`` and
``paper`` presets) on the single backend (``n_envs`` single envs, SB3's PPO) and on the batched one
twice: through SB3's ``VecEnv`` interface (SB3's PPO: numpy observations and per-world infos every
step) and device-native (:class:`sb3_divmorph.algos.device_ppo.DevicePPO`: rollouts through
``step_tensors``, the buffer, GAE and normalisation on the device), each with its rollout/update
split. Warm-up (kernel compilation, CUDA graph capture, the first rollout) is excluded from every
timing and reported separately.

Last, counts that explain the per-step cost (``--count-robots``, on each device): kernel nodes per
robot in one control step's physics program (``RobotWorlds._step_physics``: Warp launches, memsets,
copies and conditional nodes, counted as the graph is captured, and the kernels it actually runs
once with the solver's iterations), graph launches and torch calls per env step, and the host <->
device copies and waits per step of the VecEnv path against the device path
(:class:`sb3_divmorph.algos.device_ppo.HostTransferCounter`).

Usage::

    python benchmarks/batched_throughput.py [--robots 10 100] [--worlds 1 8 32] [--devices cpu cuda]
    python benchmarks/batched_throughput.py --tasks --robots --ppo-robots 2 --ppo-worlds 8 --out results/x.md  # PPO and counts only

Writes ``results/batched_throughput.md`` (interrupted with Ctrl-C or ``timeout -s INT``, it writes the
rows measured so far). Targets on one H100: >= 200k env steps/s on FT across 100 robots, >= 100k on
VT, PPO end to end >= 30k samples/s with the paper-size MetaMorph.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from contextlib import nullcontext
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
    before = torch.cat([block.readings for block in env.blocks]).clone()
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for _ in range(10):
            env.step_tensors(random())
        steps += 10
        _synchronize(env)
    if torch.equal(before, torch.cat([block.readings for block in env.blocks])):
        raise RuntimeError(
            "the worlds did not move while timed: the physics graphs replayed nothing (a capture that "
            "recorded no kernel?); these steps/s would be meaningless"
        )
    return n * steps / (time.perf_counter() - start), warmup


def _synchronize(env) -> None:
    if env.torch_device.type == "cuda":
        torch.cuda.synchronize(env.torch_device)


def ppo_steps_per_second(
    make_env, preset: str, device: str, n_steps: int, rollouts: int, algo: str = "sb3"
) -> tuple[float, int, float, float]:
    """End-to-end PPO samples/s (rollouts + updates) after one warm-up rollout.

    :param make_env: builds the (monitored) VecEnv.
    :param preset: the MetaMorph policy's preset (``small``, ``paper``); a ``+bf16`` suffix (``paper+bf16``)
        runs its Transformer under bfloat16 autocast (``mixed_precision=True``).
    :param device: torch device of the policy.
    :param n_steps: steps per env per rollout.
    :param rollouts: timed rollouts (each followed by its update).
    :param algo: ``"sb3"`` (SB3's PPO, through the VecEnv interface) or ``"device"`` (DevicePPO).
    :return: (samples/s, rollout size, seconds collecting, seconds updating) of the timed rollouts.
    """
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    import sb3_divmorph  # noqa: F401  (policy aliases)
    from sb3_divmorph.algos.device_ppo import DevicePPO

    venv = VecNormalize(make_env(), norm_obs_keys=["proprioceptive", "hfield"], norm_reward=True)
    rollout = venv.num_envs * n_steps
    cls = DevicePPO if algo == "device" else PPO
    model = cls(
        "MetaMorphPolicy",
        venv,
        n_steps=n_steps,
        batch_size=min(rollout, 4096),
        n_epochs=2,
        policy_kwargs={"preset": preset.removesuffix("+bf16"), "mixed_precision": preset.endswith("+bf16")},
        device=device,
        seed=0,
    )
    split = {"rollout": 0.0, "update": 0.0}

    def timed(name, method):
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                if torch.cuda.is_available() and model.device.type == "cuda":
                    torch.cuda.synchronize(model.device)
                split[name] += time.perf_counter() - start

        return run

    model.collect_rollouts = timed("rollout", model.collect_rollouts)
    model.train = timed("update", model.train)
    model.learn(rollout)
    split.update(rollout=0.0, update=0.0)
    start = time.perf_counter()
    model.learn(rollouts * rollout, reset_num_timesteps=False)
    return rollouts * rollout / (time.perf_counter() - start), rollout, split["rollout"], split["update"]


class _WarpCounter:
    """Counts Warp operations while active: kernel launches, memsets (``zero_``/``fill_``), copies
    and conditional nodes (``capture_while``/``capture_if``); operations nested in a counted one
    (a ``fill_`` that launches a kernel) count once. Inside a capture each is one graph node; run
    eagerly, a ``capture_while`` body counts once per iteration. Launches over zero threads (a
    kernel for a feature the model lacks: tendons, flexes, equality constraints) are not graph
    nodes (Warp skips them); they are counted apart as ``empty``."""

    def __init__(self):
        self.counts = {"kernels": 0, "memsets": 0, "copies": 0, "conditionals": 0, "empty": 0}

    def __enter__(self):
        import warp as wp

        self._saved = []
        inside = [False]

        def patch(owner, name, kind, leaf=True):
            original = getattr(owner, name)

            def counted(*args, **kwargs):
                if inside[0]:
                    return original(*args, **kwargs)
                if kind == "kernels":
                    dim = kwargs.get("dim", args[1] if len(args) > 1 else 1)
                    if int(np.prod(dim if isinstance(dim, (tuple, list)) else [dim])) == 0:
                        self.counts["empty"] += 1
                        return original(*args, **kwargs)
                self.counts[kind] += 1
                if not leaf:
                    return original(*args, **kwargs)
                inside[0] = True
                try:
                    return original(*args, **kwargs)
                finally:
                    inside[0] = False

            self._saved.append((owner, name, original))
            setattr(owner, name, counted)

        patch(wp, "launch", "kernels")
        patch(wp, "launch_tiled", "kernels")
        patch(wp, "copy", "copies")
        patch(wp.array, "zero_", "memsets")
        patch(wp.array, "fill_", "memsets")
        patch(wp, "capture_while", "conditionals", leaf=False)
        patch(wp, "capture_if", "conditionals", leaf=False)
        return self

    def __exit__(self, *exc):
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)


def launch_counts(task: str, files: list[Path], worlds: int, device: str) -> dict:
    """Kernel nodes per robot in one control step's physics program, and per-step launches and
    torch calls of the whole env (see the module docstring)."""
    import warp as wp
    from torch.overrides import TorchFunctionMode

    from unimal_envs.batched import make_batched_env

    env = make_batched_env(task, morphologies=files, worlds_per_robot=worlds, device=device, seed=0, terrain_variants=2)
    env.reset_tensors()
    generator = torch.Generator(device=env.torch_device).manual_seed(0)
    random = lambda: torch.rand((env.num_envs, C.ACTION_DIM), generator=generator, device=env.torch_device) * 2 - 1  # noqa: E731
    for _ in range(20):  # eager (compiles), captures, replays; robots in contact with the ground
        env.step_tensors(random())
    env.blocks[0].actions.copy_(random())
    captured, eager = [], []
    for group in env.blocks[0].groups:
        with wp.ScopedDevice(group.device), wp.ScopedStream(group.stream) if group.stream is not None else nullcontext():
            with _WarpCounter() as counter, wp.ScopedCapture(device=group.device, stream=group.stream):
                group._step_physics()
            captured.append(counter.counts)
            with _WarpCounter() as counter:
                group._step_physics()
            eager.append(counter.counts)

    class TorchCalls(TorchFunctionMode):
        calls = 0

        def __torch_function__(self, func, types, args=(), kwargs=None):
            TorchCalls.calls += 1
            return func(*args, **(kwargs or {}))

    launches = [0]
    original = wp.capture_launch

    def counting_launch(*args, **kwargs):
        launches[0] += 1
        return original(*args, **kwargs)

    wp.capture_launch = counting_launch
    try:
        with TorchCalls():
            for _ in range(10):
                env.step_tensors(random())
    finally:
        wp.capture_launch = original
    env.close()
    return {
        "captured": captured,
        "eager": eager,
        "graph_launches": launches[0] / 10,
        "torch_calls": TorchCalls.calls / 10,
        "robots": len(files),
        "envs": env.num_envs,
    }


def transfer_counts(files: list[Path], worlds: int, device: str, n_steps: int = 8, max_episode_steps: int = 1000) -> dict:
    """Per-step host <-> device copies and waits of one PPO rollout on the batched env, through
    SB3's VecEnv interface and through DevicePPO (tiny MetaMorph policy, VecNormalize as the
    pipeline uses it); and the per-world Python objects the VecEnv path builds per step."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    import sb3_divmorph  # noqa: F401
    from sb3_divmorph.algos.device_ppo import DevicePPO, HostTransferCounter
    from unimal_envs.batched import make_batched_env
    from unimal_envs.batched.env import BatchedUnimalEnv

    tiny = dict(d_model=16, n_layers=1, ff_dim=32)
    rows = {}
    for name, cls in (("VecEnv (SB3 PPO)", PPO), ("device (DevicePPO)", DevicePPO)):
        env = make_batched_env(
            "FT", morphologies=files, worlds_per_robot=worlds, device=device, seed=0, max_episode_steps=max_episode_steps
        )
        venv = VecNormalize(VecMonitor(env), norm_obs_keys=["proprioceptive", "hfield"])
        model = cls(
            "MetaMorphPolicy",
            venv,
            n_steps=2 * n_steps,
            batch_size=2 * n_steps * env.num_envs,
            n_epochs=1,
            seed=0,
            policy_kwargs=tiny,
            device=device,
        )
        _, callback = model._setup_learn(10 * n_steps * env.num_envs, None)
        model.collect_rollouts(model.env, callback, model.rollout_buffer, n_steps)  # warm-up
        infos, ended = [0, 0], []
        original_wait, original_step = BatchedUnimalEnv.step_wait, BatchedUnimalEnv.step_tensors

        # B023: these wrappers read this iteration's originals and counters, and are only called (and put back) within it.
        def counting_step_wait(self):
            out = original_wait(self)  # noqa: B023
            infos[0] += len(out[3])  # noqa: B023
            infos[1] += sum("terminal_observation" in info for info in out[3])  # noqa: B023
            return out

        def recording_step_tensors(self, actions):
            out = original_step(self, actions)  # noqa: B023
            ended.append(out[2] | out[3])  # noqa: B023
            return out

        BatchedUnimalEnv.step_wait, BatchedUnimalEnv.step_tensors = counting_step_wait, recording_step_tensors
        counted = {}
        try:
            for steps in (n_steps, 2 * n_steps):  # the difference is what a step costs, when steps cost alike
                infos[:], ended[:] = [0, 0], []
                with HostTransferCounter() as counter:
                    model.collect_rollouts(model.env, callback, model.rollout_buffer, steps)
                counted[steps] = dict(
                    counter.counts, info_dicts=infos[0], terminal_dicts=infos[1], episodes=int(sum(int(e.sum()) for e in ended))
                )
        finally:
            BatchedUnimalEnv.step_wait, BatchedUnimalEnv.step_tensors = original_wait, original_step
        longer = counted[2 * n_steps]
        per_step = {k: v / (2 * n_steps) for k, v in longer.items()}  # averaged, per-rollout work included
        per_rollout = {k: longer[k] - 2 * (longer[k] - counted[n_steps][k]) for k in longer}
        rows[name] = {
            "per_step": per_step,
            "per_rollout": per_rollout,
            "envs": env.num_envs,
            "episodes": longer["episodes"],
            "steps": 2 * n_steps,
        }
    return rows


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
    parser.add_argument(
        "--ppo-presets",
        nargs="*",
        default=["small", "paper"],
        help="policy presets of the PPO rows; a +bf16 suffix (paper+bf16) runs the Transformer under bfloat16 autocast",
    )
    parser.add_argument(
        "--ppo-algos",
        nargs="*",
        default=["sb3", "device"],
        help="batched PPO paths: sb3 (SB3's PPO through the VecEnv interface), device (DevicePPO)",
    )
    parser.add_argument("--ppo-single-envs", type=int, default=8, help="single C envs of the CPU PPO row (0: skip it)")
    parser.add_argument("--count-robots", type=int, default=10, help="robots of the launch and copy counts (0: skip them)")
    parser.add_argument("--count-worlds", type=int, default=8, help="worlds per robot of the launch and copy counts")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    from unimal_envs.batched import make_batched_env

    torch.set_num_threads(1)
    devices = [d for d in args.devices if d != "cuda" or torch.cuda.is_available()]
    skipped = [d for d in args.devices if d not in devices]
    env_rows: list[tuple] = []
    ppo_rows: list[tuple] = []
    counts: dict[str, dict] = {}
    ppo_files = morphology_files(args.morphologies)[: args.ppo_robots]
    interrupted = False
    try:
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
                        print(
                            f"{task} {len(files)} robots batched {device} W={worlds}: {rate:.0f} steps/s "
                            f"({rate / single:.1f}x single; warm-up {warmup:.1f} s)",
                            flush=True,
                        )

        files = ppo_files
        from divmorph.pipeline.envs import make_vec_env

        for preset in args.ppo_presets:
            single_envs = args.ppo_single_envs
            if single_envs:
                rate, rollout, collect, update = ppo_steps_per_second(
                    lambda: make_vec_env("Unimal-FT-v0", single_envs, 0, 1000, morphologies=files),  # noqa: B023 (called here)
                    preset,
                    "cpu",
                    64,
                    2,
                )
                ppo_rows.append((preset, f"single x {single_envs} (cpu)", single_envs, rollout, rate, collect, update))
                print(f"PPO {preset} single x{single_envs}: {rate:.0f} steps/s", flush=True)
            for device in devices:
                for worlds in args.ppo_worlds:
                    make = lambda: make_vec_env("Unimal-FT-v0", 0, 0, 1000, "batched", worlds, device, morphologies=files)  # noqa: E731,B023 (called in this iteration)
                    for algo in args.ppo_algos:
                        rate, rollout, collect, update = ppo_steps_per_second(make, preset, device, 16, 2, algo)
                        path = "VecEnv, SB3 PPO" if algo == "sb3" else "device, DevicePPO"
                        ppo_rows.append(
                            (
                                preset,
                                f"batched ({device}, {path}), {worlds} worlds/robot",
                                len(files) * worlds,
                                rollout,
                                rate,
                                collect,
                                update,
                            )
                        )
                        print(
                            f"PPO {preset} batched {device} {algo} W={worlds}: {rate:.0f} steps/s "
                            f"(rollout {collect:.2f} s, update {update:.2f} s)",
                            flush=True,
                        )

        if args.count_robots:
            count_files = morphology_files(args.morphologies)[: args.count_robots]
            for device in devices:
                for task in ("FT", "VT"):
                    counts[f"launches {task} {device}"] = launch_counts(task, count_files, args.count_worlds, device)
                    print(f"counted launches {task} {device}", flush=True)
                counts[f"transfers {device}"] = transfer_counts(count_files, args.count_worlds, device)
                print(f"counted transfers {device}", flush=True)

    except KeyboardInterrupt:  # a time box ran out: keep what was measured
        interrupted = True
        print("interrupted: writing the rows measured so far", flush=True)

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
    if interrupted:
        lines.append("**Interrupted** (a time limit ran out): the rows below are those measured before it; the rest are missing.")
    if skipped:
        lines.append(f"No {', '.join(skipped)} device on this machine: those rows are missing; run the same command on a GPU machine.")
    if devices == ["cpu"]:
        lines.append(
            "**Every batched row and count here is CPU Warp** (MuJoCo Warp's kernels compiled for the CPU, one core): "
            "a correctness backend, not a measurement of the GPU."
        )
    if env_rows:
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
        lines.append(
            f"| {task} | {robots} | {backend} | {worlds} | {envs} | {rate:,.0f} | {rate / singles[task, robots]:.2f}x "
            f"| {warmup:.1f} | {overflow} |"
        )
    if ppo_rows:
        single = f"single rollouts are 64 steps x {args.ppo_single_envs} envs, " if args.ppo_single_envs else ""
        lines += [
            "",
            f"## PPO end to end (FT, {len(ppo_files)} robots, MetaMorph policy)",
            "",
            "Samples/s of `learn` over two rollouts (collection + 2 epochs of updates, batch <= 4096) after one warm-up rollout; "
            f"{single}batched rollouts 16 steps x all worlds. Batched rows run twice: SB3's PPO "
            "through the VecEnv interface (numpy observations and one info dict per world every step) and DevicePPO "
            "(rollouts through `step_tensors`, buffer, GAE and VecNormalize's arithmetic on the device). Rollout and update "
            "are the seconds of the two timed rollouts spent collecting and in PPO's update (CUDA synchronised at the boundaries).",
            "",
            "| preset | backend | envs | rollout | PPO steps/s | rollout (s) | update (s) | rollout share |",
            "|---|---|---|---|---|---|---|---|",
        ]
    for preset, backend, envs, rollout, rate, collect, update in ppo_rows:
        lines.append(
            f"| {preset} | {backend} | {envs} | {rollout} | {rate:,.0f} | {collect:.2f} | {update:.2f} "
            f"| {collect / max(collect + update, 1e-9):.0%} |"
        )
    lines += _count_lines(counts, args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


def _count_lines(counts: dict[str, dict], args) -> list[str]:
    """The markdown of the launch and copy counts."""
    if not counts:
        return []
    lines = [
        "",
        f"## Kernel launches and host <-> device traffic per env step ({args.count_robots} robots x {args.count_worlds} worlds)",
        "",
        "Physics program of one control step (`RobotWorlds._step_physics`: actions onto the motors, 4 MuJoCo Warp substeps, "
        "kinematics, the observation kernel), per robot. *Graph nodes*: Warp operations recorded while the program is "
        "captured (kernels, memsets, copies; a conditional node holds the solver's iteration loop, whose body is counted "
        "once). *Run eagerly*: the operations one step actually executes kernel by kernel, solver iterations included. "
        "min-max over the robots.",
        "",
        "| task | device | graph nodes: kernels | memsets | copies | conditionals | zero-size launches (no node) "
        "| run eagerly: kernels | memsets + copies | graph launches per env step | torch calls per env step |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    span = lambda rows, key: f"{min(r[key] for r in rows)}-{max(r[key] for r in rows)}"  # noqa: E731
    for name, c in counts.items():
        if not name.startswith("launches"):
            continue
        _, task, device = name.split()
        cap, eager = c["captured"], c["eager"]
        eager_mem = [{"n": r["memsets"] + r["copies"]} for r in eager]
        lines.append(
            f"| {task} | {device} | {span(cap, 'kernels')} | {span(cap, 'memsets')} | {span(cap, 'copies')} "
            f"| {span(cap, 'conditionals')} | {span(cap, 'empty')} | {span(eager, 'kernels')} | {span(eager_mem, 'n')} "
            f"| {c['graph_launches']:.0f} ({c['robots']} robots) | {c['torch_calls']:.0f} |"
        )
    lines += [
        "",
        "Graph launches: one captured physics graph per robot per step (plus one `sync` graph per robot on steps where a "
        "world resets). Torch calls: every torch function the env's step makes (actions, readings, rewards, "
        "terminations, observations, auto-reset), for all robots together; on CUDA each is at most one small kernel.",
        "",
        "Host <-> device traffic of one 16-step PPO rollout on FT (tiny MetaMorph policy, VecNormalize on "
        "proprioceptive/hfield, the timestep limit 1000: the episodes that end are falls), counted with "
        "`HostTransferCounter` (on a CPU-only machine: the calls that would be copies or waits on CUDA). Per step: the "
        "rollout's totals over its 16 steps (the per-rollout work included). Fixed per rollout (from a 16- minus an "
        "8-step rollout; exact only where every step costs the same, i.e. the device path).",
        "",
        "| path | envs | episodes ended | to host per step (calls / KB) | host to device per step (calls / KB) "
        "| waits per step | per-world info dicts per step | torch calls per step | fixed per rollout: copies (calls / KB), waits |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, c in counts.items():
        if not name.startswith("transfers"):
            continue
        device = name.split()[1]
        for path, row in c.items():
            s, r = row["per_step"], row["per_rollout"]
            fixed = (
                (f"{r['to_host'] + r['to_device']:.0f} / {(r['to_host_bytes'] + r['to_device_bytes']) / 1024:.0f}, {r['syncs']:.0f}")
                if path.startswith("device")
                else "-"
            )
            lines.append(
                f"| {path} ({device}) | {row['envs']} | {row['episodes']} | {s['to_host']:.1f} / {s['to_host_bytes'] / 1024:.0f} "
                f"| {s['to_device']:.1f} / {s['to_device_bytes'] / 1024:.0f} | {s['syncs']:.1f} | {s['info_dicts']:.0f} "
                f"| {s['calls']:.0f} | {fixed} |"
            )
    return lines


def _version(name: str) -> str:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    main()
