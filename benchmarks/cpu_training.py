"""End-to-end CPU training rate against SB3's own PPO on Ant-v5, with the time split and the floor.

    python benchmarks/cpu_training.py                         # the cpu100 teacher's settings -> results/cpu_training.md
    python benchmarks/cpu_training.py --iterations 1 --repeats 1 --n-envs 2 --n-steps 64 --batch 128 --output /tmp/x.md
    python benchmarks/cpu_training.py --paths metamorph divmorph --vs-code /tmp/before   # against an earlier checkout

**Paths**, each a PPO run built the way the pipeline builds it, timed in one process with one torch thread,
interleaved repeat by repeat (so a busy machine slows all of them alike; the ratios are what carries over):

- ``metamorph``: the cpu100 FT teacher (MetaMorph, width 32, one layer; ``divmorph.pipeline.teachers.teacher_run``
  of the ``cpu100`` profile with the settings below) on the 100 official training robots;
- ``divmorph``: the ``cpu100-transfer`` student's policy (DivMorph, 24 learngenes + 4 + 4 tailors) trained by
  PPO on the same env and settings (its cost per sample against MetaMorph's);
- ``ant``: SB3's PPO with ``MlpPolicy`` on Gymnasium's ``Ant-v5``: the same n_envs, n_steps, minibatch, epochs
  and ``VecNormalize``.

Each repeat runs ``--iterations`` rollout+update cycles of every path after one warm-up cycle, and reports
samples (env steps) per second. **The time split** of each path (the share of its wall time) comes from timers
around: MuJoCo's ``mj_step`` (physics), the env's ``step``/``reset`` (env Python = that minus physics), the
VecEnv stack's ``step`` (VecEnv = that minus the env), the policy's rollout ``forward`` and ``predict_values``,
the update's ``evaluate_actions`` (update forward), ``backward`` and the optimiser step; the rest (buffers,
GAE, SB3's loop) is "other".

**The floor** of one core: physics alone (``mj_step`` of the same robots and frame skip, random controls),
plus the FLOPs of a training sample (the rollout forward's and the update's, counted by
``torch.utils.flop_counter`` on one minibatch, times the epochs) at this core's large-sgemm rate
(a 1024-square float32 matmul). Samples/s at the floor = 1 / (1 / physics rate + FLOPs per sample / sgemm rate).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import platform
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch as th  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
_INHERITED = object()
PARTS = ["physics", "env Python", "VecEnv", "rollout forward", "update forward", "update backward", "optimiser", "other"]


class Timers:
    """Accumulated seconds per part; nested timers of the same part count once (the outermost)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._depth: dict[str, int] = defaultdict(int)

    def wrap(self, part: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            self._depth[part] += 1
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self._depth[part] -= 1
                if self._depth[part] == 0:
                    self.seconds[part] += time.perf_counter() - start

        return timed


class _TimedModule:
    """A module proxy whose ``mj_step`` is timed (the envs call ``mujoco.mj_step`` through their module)."""

    def __init__(self, module: Any, timers: Timers) -> None:
        self._module = module
        self.mj_step = timers.wrap("physics", module.mj_step)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._module, name)


@contextlib.contextmanager
def instrumented(model: Any, timers: Timers, env_modules: list[Any], env_classes: list[type]) -> Iterator[None]:
    """Timers around every part of ``model.learn`` (restored afterwards)."""
    import mujoco

    saved: list[tuple[Any, str, Any]] = []

    def patch(owner: Any, name: str, value: Any) -> None:
        # a class's own attribute is put back; an inherited or instance one is deleted again
        saved.append((owner, name, owner.__dict__.get(name, _INHERITED) if isinstance(owner, type) else _INHERITED))
        setattr(owner, name, value)

    for module in env_modules:
        patch(module, "mujoco", _TimedModule(mujoco, timers))
    for cls in env_classes:
        patch(cls, "step", timers.wrap("env", cls.step))
        patch(cls, "reset", timers.wrap("env", cls.reset))
    venv = model.env
    patch(venv, "step", timers.wrap("vecenv", venv.step))
    patch(venv, "reset", timers.wrap("vecenv", venv.reset))
    policy = model.policy
    patch(policy, "forward", timers.wrap("rollout forward", policy.forward))
    patch(policy, "predict_values", timers.wrap("rollout forward", policy.predict_values))
    patch(policy, "evaluate_actions", timers.wrap("update forward", policy.evaluate_actions))
    patch(policy.optimizer, "step", timers.wrap("optimiser", policy.optimizer.step))
    patch(th.Tensor, "backward", timers.wrap("update backward", th.Tensor.backward))
    try:
        yield
    finally:
        for owner, name, value in reversed(saved):
            if value is _INHERITED:
                delattr(owner, name)
            else:
                setattr(owner, name, value)


def split(timers: Timers, wall: float) -> dict[str, float]:
    """Seconds per reported part (the nested ones taken out of their parents)."""
    s = timers.seconds
    parts = {
        "physics": s["physics"],
        "env Python": s["env"] - s["physics"],
        "VecEnv": s["vecenv"] - s["env"],
        "rollout forward": s["rollout forward"],
        "update forward": s["update forward"],
        "update backward": s["update backward"],
        "optimiser": s["optimiser"],
    }
    parts["other"] = wall - sum(parts.values())
    return parts


# -- the paths ---------------------------------------------------------------------------------------------


def unimal_model(policy: str, policy_kwargs: dict[str, Any], args: argparse.Namespace, folder: Path) -> Any:
    """PPO on the cpu100 FT teacher's env (100 official training robots, its VecNormalize, its zoo entry's PPO
    settings), built as the pipeline builds a teacher; ``policy_kwargs`` replace the teacher's network."""
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.teachers import teacher_run

    overrides: dict[str, Any] = {
        f"teachers.overrides.{k}": v
        for k, v in dict(n_envs=args.n_envs, n_steps=args.n_steps, batch_size=args.batch, n_epochs=args.epochs).items()
    }
    if policy_kwargs:
        overrides["teachers.policy_kwargs"] = dict(policy_kwargs)
    profile = load_profile("cpu100", overrides=overrides)
    return teacher_run(profile, folder, "FT", progress_bar=False, policy=policy).make_model()


def ant_model(args: argparse.Namespace) -> Any:
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    venv = VecNormalize(make_vec_env("Ant-v5", n_envs=args.n_envs, seed=0), gamma=0.99)
    return PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=args.batch, n_epochs=args.epochs, seed=0, device="cpu")


def build_paths(args: argparse.Namespace, folder: Path) -> dict[str, tuple[Any, list[Any], list[type]]]:
    """``{name: (model, env modules whose mujoco to time, env classes whose step to time)}``."""
    import gymnasium.envs.mujoco.mujoco_env as gym_mujoco
    from gymnasium.envs.mujoco.ant_v5 import AntEnv

    import unimal_envs.env as unimal_env
    from divmorph.pipeline.config import load_profile

    student = load_profile("cpu100-transfer").student.policy_kwargs
    built = {}
    for name in args.paths:
        if name == "metamorph":
            built[name] = (unimal_model("MetaMorphPolicy", {}, args, folder / name), [unimal_env], [unimal_env.UnimalEnv])
        elif name == "divmorph":
            built[name] = (unimal_model("DivMorphPolicy", dict(student), args, folder / name), [unimal_env], [unimal_env.UnimalEnv])
        elif name == "ant":
            built[name] = (ant_model(args), [gym_mujoco], [AntEnv])
        else:
            raise SystemExit(f"unknown path {name!r}; paths: metamorph, divmorph, ant")
    return built


def cycle(model: Any, args: argparse.Namespace, iterations: int) -> int:
    """Run ``iterations`` rollout+update cycles; the env steps they took."""
    before = model.num_timesteps
    model.learn(iterations * args.n_envs * args.n_steps, reset_num_timesteps=False)
    return model.num_timesteps - before


# -- the floor ---------------------------------------------------------------------------------------------


def sgemm_rate(size: int = 1024, repeats: int = 5) -> float:
    """FLOP/s of a large float32 matmul on one thread."""
    a, b = th.randn(size, size), th.randn(size, size)
    a @ b
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - start)
    return 2 * size**3 / min(times)


def physics_rate(model: Any, env_classes: list[type], seconds: float = 3.0) -> float:
    """Env steps/s of MuJoCo alone on the path's own worlds (each env's current robot, random controls, the env's frame skip)."""
    import mujoco

    envs = [env.unwrapped for env in model.env.unwrapped.envs]
    rng = np.random.default_rng(0)
    if hasattr(envs[0], "_world") and envs[0]._world is not None:
        worlds = [(env._world.model, env._world.data) for env in envs]
        substeps = 4
    else:
        worlds = [(env.model, env.data) for env in envs]
        substeps = envs[0].frame_skip
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for m, d in worlds:
            d.ctrl[:] = rng.uniform(-1, 1, m.nu)
            mujoco.mj_step(m, d, nstep=substeps)
            steps += 1
    return steps / (time.perf_counter() - start)


def flops_per_sample(model: Any, args: argparse.Namespace) -> float:
    """FLOPs of one training sample: its rollout forward plus ``n_epochs`` update passes (forward + backward)."""
    from torch.utils.flop_counter import FlopCounterMode

    policy = model.policy
    buffer = model.rollout_buffer
    batch = next(buffer.get(args.batch))
    counter = FlopCounterMode(display=False)
    policy.set_training_mode(True)
    with counter:
        values, log_prob, entropy = policy.evaluate_actions(batch.observations, batch.actions)
        (values.sum() + log_prob.sum() + (entropy.sum() if entropy is not None else 0)).backward()
    update = counter.get_total_flops() / args.batch * args.epochs
    policy.set_training_mode(False)
    observations = (
        {k: v[: args.n_envs] for k, v in batch.observations.items()}
        if isinstance(batch.observations, dict)
        else batch.observations[: args.n_envs]
    )
    with th.no_grad():
        policy(observations)  # a rollout builds its stacked weights once (per rollout and robot batch): count a step after
        counter = FlopCounterMode(display=False)
        with counter:
            policy(observations)
    return update + counter.get_total_flops() / args.n_envs


# -- the table ---------------------------------------------------------------------------------------------


def measure(args: argparse.Namespace) -> str:
    th.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        paths = build_paths(args, Path(tmp))
        for model, _, _ in paths.values():
            cycle(model, args, 1)  # warm-up: allocations, first resets, the normaliser's first statistics
        rates: dict[str, list[float]] = defaultdict(list)
        parts: dict[str, dict[str, float]] = {name: defaultdict(float) for name in paths}
        for _ in range(args.repeats):
            for name, (model, modules, classes) in paths.items():
                timers = Timers()
                with instrumented(model, timers, modules, classes):
                    start = time.perf_counter()
                    steps = cycle(model, args, args.iterations)
                    wall = time.perf_counter() - start
                rates[name].append(steps / wall)
                for part, seconds in split(timers, wall).items():
                    parts[name][part] += seconds / wall / args.repeats
        floors = {}
        sgemm = sgemm_rate()
        for name, (model, _, classes) in paths.items():
            physics = physics_rate(model, classes)
            flops = flops_per_sample(model, args)
            floors[name] = (physics, flops, 1 / (1 / physics + flops / sgemm))
    args.rates = {name: list(values) for name, values in rates.items()}
    median = {name: statistics.median(values) for name, values in rates.items()}
    reference = "metamorph" if "metamorph" in median else next(iter(median))
    lines = [
        f"# CPU training rate: {', '.join(paths)} (one torch thread, one process)",
        "",
        f"{datetime.date.today()}, {platform.node()}, {platform.processor() or platform.machine()}, load average "
        f"{os.getloadavg()[0]:.1f} at the end; torch {th.__version__}; {args.n_envs} envs x {args.n_steps} steps, "
        f"minibatch {args.batch}, {args.epochs} epochs, VecNormalize; {args.iterations} cycles per repeat, median of {args.repeats} "
        f"interleaved repeats after one warm-up cycle. Command: `python benchmarks/cpu_training.py {' '.join(args.argv)}`.",
        "",
        f"| path | samples/s (each repeat) | vs {reference} | vs ant | floor samples/s (physics steps/s; FLOPs per sample) | share of the floor |",
        "|---|---|---:|---:|---|---:|",
    ]
    for name, rate in median.items():
        physics, flops, floor = floors[name]
        versus_ant = f"{rate / median['ant']:.2f}x" if "ant" in median else "–"
        lines.append(
            f"| {name} | {rate:,.0f} ({', '.join(f'{r:,.0f}' for r in rates[name])}) | {rate / median[reference]:.2f}x | {versus_ant} | "
            f"{floor:,.0f} ({physics:,.0f}; {flops / 1e6:.2f} MFLOP) | {rate / floor:.2f} |"
        )
    lines += ["", f"Time split (share of each path's wall time; sgemm rate {sgemm / 1e9:.1f} GFLOP/s):", ""]
    lines += ["| path | " + " | ".join(PARTS) + " |", "|---|" + "---:|" * len(PARTS)]
    for name in paths:
        lines.append(f"| {name} | " + " | ".join(f"{100 * parts[name][p]:.1f}%" for p in PARTS) + " |")
    return "\n".join(lines) + "\n"


def versus(args: argparse.Namespace) -> str:
    """Today's code against ``--vs-code`` (a checkout of an earlier commit): one repeat of every path in a fresh
    process per code and round, the two codes alternating round by round (``PYTHONPATH`` picks the code; this
    script's measurement is the same for both), so a machine whose speed drifts slows both alike."""
    import json
    import subprocess
    import sys

    codes = {"today": ROOT, "before": Path(args.vs_code).resolve()}
    rates: dict[str, dict[str, list[float]]] = {code: defaultdict(list) for code in codes}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.repeats):
            for code, folder in codes.items():
                out = Path(tmp) / f"{code}-{round_}.json"
                line = [sys.executable, __file__, "--paths", *args.paths, "--repeats", "1", "--iterations", str(args.iterations)]
                line += [
                    "--n-envs",
                    str(args.n_envs),
                    "--n-steps",
                    str(args.n_steps),
                    "--batch",
                    str(args.batch),
                    "--epochs",
                    str(args.epochs),
                ]
                line += ["--output", str(Path(tmp) / "ignored.md"), "--rates-json", str(out)]
                # run in the checkout, so that its own zoo_configs/ (a profile's relative path) is the one read
                subprocess.run(line, check=True, env={**os.environ, "PYTHONPATH": str(folder)}, cwd=folder, stdout=subprocess.DEVNULL)
                for name, values in json.loads(out.read_text()).items():
                    rates[code][name] += values
    commit = subprocess.run(
        ["git", "-C", str(codes["before"]), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    lines = [
        f"# CPU training rate: today's code against {commit or codes['before']} (one torch thread per process)",
        "",
        f"{datetime.date.today()}, {platform.node()}, load average {os.getloadavg()[0]:.1f} at the end; {args.n_envs} envs x "
        f"{args.n_steps} steps, minibatch {args.batch}, {args.epochs} epochs; {args.repeats} rounds, each code's repeat in a "
        f"fresh process, alternating. Command: `python benchmarks/cpu_training.py {' '.join(args.argv)}`.",
        "",
        f"| path | today samples/s (each round) | {commit or 'before'} samples/s (each round) | today / before (median of the rounds' ratios) |",
        "|---|---|---|---:|",
    ]
    for name in args.paths:
        today, before = rates["today"][name], rates["before"][name]
        ratio = statistics.median(a / b for a, b in zip(today, before))
        lines.append(
            f"| {name} | {statistics.median(today):,.0f} ({', '.join(f'{r:,.0f}' for r in today)}) | "
            f"{statistics.median(before):,.0f} ({', '.join(f'{r:,.0f}' for r in before)}) | {ratio:.2f}x |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    import json
    import sys

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--paths", nargs="+", default=["metamorph", "divmorph", "ant"])
    parser.add_argument("--n-envs", type=int, default=16)
    parser.add_argument("--n-steps", type=int, default=512)
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=1, help="rollout+update cycles per path and repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", type=Path, default=None, help="default: results/cpu_training.md (with --vs-code: cpu_training_vs.md)")
    parser.add_argument("--vs-code", type=Path, default=None, help="a checkout of an earlier commit: today's code against it")
    parser.add_argument("--rates-json", type=Path, default=None, help=argparse.SUPPRESS)  # one repeat's rates, for --vs-code
    args = parser.parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else argv
    if args.vs_code is not None:
        text = versus(args)
        output = args.output or ROOT / "results" / "cpu_training_vs.md"
    else:
        text = measure(args)
        output = args.output or ROOT / "results" / "cpu_training.md"
        if args.rates_json is not None:
            args.rates_json.write_text(json.dumps(args.rates))
    output.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
