"""Reliability of the UNIMAL envs: a morphology fuzz and a long multi-task memory soak.

**Fuzz.** ``--fuzz-count`` robots are generated with the project's generator
(``generate_unimal(seed)`` for consecutive seeds from ``--fuzz-seed``, written in the unimals_100
layout to a temporary directory like the shipped sets), loaded through the loader, and each one
drives a ``Unimal-FT-v0`` env (``gym.make``, so with the TimeLimit/OrderEnforcing/PassiveEnvChecker
wrappers) for ``--fuzz-steps`` uniform random actions in [-1, 1], resetting on episode end. Every
observation must match the observation space (keys, shapes, float32, bounds) and hold only finite
values, and every reward must be finite. A failing robot never stops the fuzz: its seed, stage and
error are recorded.

**Soak.** ``--soak-steps`` env steps over all 10 tasks (``Unimal-<task>-v0``), each env on the first
``--soak-morphologies`` robots of the shipped train set (more robots than the default world cache of
16, so compiled worlds keep being evicted and rebuilt), random actions, round-robin over the tasks in
chunks of ``--chunk`` steps. The process RSS (``VmRSS`` of ``/proc/self/status``) is sampled every
``--sample-every`` steps; the report gives RSS after the warm-up (at least ``--warmup-steps``, and
until every env's world cache is full: until then memory grows by design), its maximum, its end
value and the least-squares slope after warm-up in MB per 100k steps, the number of non-finite
values (must be 0), physics faults (``info["physics_fault"]``) and steps/s. At the end, glibc's
``malloc_trim(0)`` hands free heap pages back and RSS is read again, which tells memory still in use
from heap the allocator kept after freeing evicted worlds.

**Control.** The same soak without evictions (world cache = ``--soak-morphologies``) runs for
``--control-steps`` in a fresh spawned process: if it is flat where the soak creeps up, the creep
comes from replacing compiled worlds, not from stepping. Both RSS curves are plotted to
``results/reliability_memory.png``.

Usage::

    python benchmarks/reliability.py [--fuzz-count 1000] [--fuzz-steps 200] [--soak-steps 1000000]
                                     [--control-steps 400000]

Writes ``results/reliability.md`` and ``results/reliability_memory.png``. MuJoCo's own warnings are
counted by the script instead of being appended to ``./MUJOCO_LOG.TXT``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import multiprocessing
import os
import platform
import shlex
import sys
import tempfile
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from datetime import date
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from tqdm.auto import tqdm

import unimal_envs
from unimal_envs import contract as C
from unimal_envs.morphology.generator import generate_unimal
from unimal_envs.morphology.loader import load_morphology, morphology_files

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "results" / "reliability.md"
PLOT = ROOT / "results" / "reliability_memory.png"
MACHINE = "2-core CPU, no GPU"


# ----------------------------------------------------------------------------------------- helpers
def rss_mb() -> float:
    """Resident set size of this process in MiB (``VmRSS`` of ``/proc/self/status``)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status")


class MujocoWarnings:
    """Counts MuJoCo's warning messages (instead of letting MuJoCo append them to MUJOCO_LOG.TXT)."""

    def __init__(self):
        self.messages: Counter[str] = Counter()
        self._previous = None

    def __enter__(self):
        self._previous = mujoco.get_mju_user_warning()
        mujoco.set_mju_user_warning(self._record)
        return self

    def _record(self, message: str) -> None:
        self.messages[message.split(". Time =")[0].strip()] += 1

    def __exit__(self, *exc):
        mujoco.set_mju_user_warning(self._previous)
        return False


def observation_problems(obs: dict, space: gym.spaces.Dict) -> list[str]:
    """What is wrong with one observation (empty list: it is in the space and finite)."""
    problems = []
    if set(obs) != set(space.spaces):
        problems.append(f"keys {sorted(obs)} != {sorted(space.spaces)}")
    for key, sub in space.spaces.items():
        value = obs.get(key)
        if value is None:
            continue
        if not isinstance(value, np.ndarray) or value.shape != sub.shape or value.dtype != sub.dtype:
            problems.append(f"{key}: {getattr(value, 'shape', None)} {getattr(value, 'dtype', type(value))}, space {sub.shape} {sub.dtype}")
            continue
        finite = np.isfinite(value)
        if not finite.all():
            problems.append(f"{key}: {int((~finite).sum())} non-finite values")
        elif not sub.contains(value):
            problems.append(f"{key}: values outside [{sub.low.min()}, {sub.high.max()}]")
    return problems


# -------------------------------------------------------------------------------------------- fuzz
@dataclass
class FuzzResult:
    count: int = 0
    generated: int = 0
    compiled: int = 0
    clean: int = 0
    steps: int = 0
    episodes: int = 0
    physics_faults: int = 0
    limbs: Counter = field(default_factory=Counter)
    failures: list[tuple[int, str, str]] = field(default_factory=list)  # (seed, stage, error)
    seconds: float = 0.0
    generate_seconds: float = 0.0


def fuzz_one(seed: int, steps: int, out_dir: Path, result: FuzzResult) -> None:
    """Generate, load and run one robot; record the outcome in ``result`` (never raises)."""
    stage = "generate"
    env = None
    try:
        start = time.perf_counter()
        robot = generate_unimal(seed)
        xml_path, _ = robot.write(out_dir)
        result.generate_seconds += time.perf_counter() - start
        result.generated += 1
        stage = "load"
        morphology = load_morphology(xml_path)
        result.limbs[morphology.num_limbs] += 1
        stage = "compile"
        env = gym.make("Unimal-FT-v0", morphologies=[xml_path])
        obs, _ = env.reset(seed=seed)
        result.compiled += 1
        stage = "step"
        space = env.observation_space
        problems = [f"reset: {p}" for p in observation_problems(obs, space)]
        rng = np.random.default_rng(seed)
        actions = rng.uniform(-1.0, 1.0, size=(steps, C.ACTION_DIM)).astype(np.float32)
        result.episodes += 1
        for t, action in enumerate(actions):
            obs, reward, terminated, truncated, info = env.step(action)
            result.steps += 1
            problems += [f"step {t}: {p}" for p in observation_problems(obs, space)]
            if not (isinstance(reward, (float, int, np.floating)) and math.isfinite(reward)):
                problems.append(f"step {t}: reward {reward!r}")
            if info.get("physics_fault"):
                result.physics_faults += 1
            if terminated or truncated:
                obs, _ = env.reset()
                result.episodes += 1
                problems += [f"reset after step {t}: {p}" for p in observation_problems(obs, space)]
            if len(problems) > 5:
                break
        if problems:
            result.failures.append((seed, "check", "; ".join(problems[:5])))
        else:
            result.clean += 1
    except Exception as err:  # noqa: BLE001 - a fuzz records every failure and goes on
        last = traceback.extract_tb(err.__traceback__)[-1]
        where = f"{Path(last.filename).name}:{last.lineno}"
        result.failures.append((seed, stage, f"{type(err).__name__}: {err} ({where})"))
    finally:
        if env is not None:
            env.close()


def run_fuzz(count: int, first_seed: int, steps: int) -> FuzzResult:
    result = FuzzResult(count=count)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="unimal-fuzz-") as tmp:
        bar = tqdm(range(first_seed, first_seed + count), desc="fuzz", unit="robot")
        for seed in bar:
            fuzz_one(seed, steps, Path(tmp), result)
            bar.set_postfix(clean=result.clean, failed=len(result.failures))
    result.seconds = time.perf_counter() - start
    return result


# -------------------------------------------------------------------------------------------- soak
@dataclass
class SoakResult:
    steps: int = 0
    episodes: int = 0
    non_finite: int = 0
    physics_faults: int = 0
    bad_observations: int = 0
    seconds: float = 0.0
    samples: list[tuple[int, float]] = field(default_factory=list)  # (steps, RSS MiB)
    rss_before_envs: float = 0.0
    per_task: dict[str, Counter] = field(default_factory=dict)
    compiled_worlds: int = 0
    #: First RSS sample at which every env's world cache was full (None: never within the soak).
    caches_full_at: int | None = None
    #: RSS at the end after glibc's ``malloc_trim(0)`` (None where unavailable).
    rss_after_trim: float | None = None
    warnings: Counter = field(default_factory=Counter)
    first_problems: list[str] = field(default_factory=list)


def malloc_trim() -> bool:
    """Ask glibc to hand free heap pages back to the OS (``malloc_trim(0)``); False if unavailable."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
        return True
    except (OSError, AttributeError):
        return False


def run_soak(total: int, n_morph: int, chunk: int, sample_every: int, seed: int, cache: int, desc: str = "soak") -> SoakResult:
    with MujocoWarnings() as warnings:
        result = _soak(total, n_morph, chunk, sample_every, seed, cache, desc)
    result.warnings = warnings.messages
    return result


def run_soak_in_fresh_process(*args) -> SoakResult:
    """:func:`run_soak` in a new (spawned) interpreter, so its RSS starts from a clean heap."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(1) as pool:
        fields = pool.apply(_soak_fields, args)
    return SoakResult(**fields)


def _soak_fields(*args) -> dict:
    tqdm.set_lock(threading.RLock())  # one process, one bar: no multiprocessing semaphore to leak
    return dataclasses.asdict(run_soak(*args))


def _soak(total: int, n_morph: int, chunk: int, sample_every: int, seed: int, cache: int, desc: str) -> SoakResult:
    result = SoakResult()
    result.rss_before_envs = rss_mb()
    files = morphology_files("train")[:n_morph]
    envs = {task: gym.make(unimal_envs.env_id(task), morphologies=files, world_cache_size=cache) for task in C.TASK_NAMES}
    space = C.observation_space()
    build_counts = Counter()
    for i, (task, env) in enumerate(envs.items()):
        env.reset(seed=seed + i)
        result.per_task[task] = Counter()
        # Count world compilations (cache misses) by wrapping the env's builder.
        base = env.unwrapped
        original = base._build_world

        def counting(index, _original=original, _task=task):
            build_counts[_task] += 1
            return _original(index)

        base._build_world = counting
    rng = np.random.default_rng(seed)
    tasks = list(envs)
    isfinite = math.isfinite
    result.samples.append((0, rss_mb()))
    next_sample = sample_every
    start = time.perf_counter()
    with tqdm(total=total, desc=desc, unit="step", unit_scale=True, mininterval=2.0) as bar:
        round_index = 0
        while result.steps < total:
            task = tasks[round_index % len(tasks)]
            round_index += 1
            env, stats = envs[task], result.per_task[task]
            n = min(chunk, total - result.steps)
            actions = rng.uniform(-1.0, 1.0, size=(n, C.ACTION_DIM)).astype(np.float32)
            for action in actions:
                obs, reward, terminated, truncated, info = env.step(action)
                result.steps += 1
                bad = not isfinite(reward)
                for value in obs.values():
                    if not isfinite(float(value.sum())) and not np.isfinite(value).all():
                        bad = True
                if bad:
                    result.non_finite += 1
                    if len(result.first_problems) < 5:
                        keys = [k for k, v in obs.items() if not np.isfinite(v).all()]
                        result.first_problems.append(f"{task} step {result.steps}: reward {reward}, keys {keys}")
                if info["physics_fault"]:
                    result.physics_faults += 1
                    stats["physics_faults"] += 1
                if terminated or truncated:
                    obs, _ = env.reset()
                    result.episodes += 1
                    stats["episodes"] += 1
                    if observation_problems(obs, space):
                        result.bad_observations += 1
                if result.steps >= next_sample:
                    result.samples.append((result.steps, rss_mb()))
                    next_sample += sample_every
                    if result.caches_full_at is None and all(
                        len(e.unwrapped._worlds) >= min(e.unwrapped.world_cache_size, n_morph) for e in envs.values()
                    ):
                        result.caches_full_at = result.steps
            stats["steps"] += n
            bar.update(n)
            bar.set_postfix(rss=f"{result.samples[-1][1]:.0f}MB", faults=result.physics_faults)
    result.seconds = time.perf_counter() - start
    if result.samples[-1][0] != result.steps:
        result.samples.append((result.steps, rss_mb()))
    result.compiled_worlds = sum(build_counts.values())
    # Free-but-retained heap (allocator high-water mark) vs. memory still in use: trim, measure again.
    result.rss_after_trim = rss_mb() if malloc_trim() else None
    for task, env in envs.items():
        result.per_task[task]["worlds"] = build_counts[task]
        env.close()
    return result


def warmup_end(soak: SoakResult, minimum: int) -> int:
    """Memory baseline step: ``minimum`` steps, and not before every env's world cache is full (after
    that, compiled worlds are only replaced, never added, so memory should stay flat)."""
    return max(minimum, soak.caches_full_at or 0)


def memory_summary(samples: list[tuple[int, float]], warmup: int) -> dict:
    steps = np.array([s for s, _ in samples], dtype=float)
    rss = np.array([r for _, r in samples])
    after = steps >= warmup
    if after.sum() < 2:  # short runs: use everything after the first sample
        after = steps > 0
    start_index = int(np.flatnonzero(after)[0])
    slope = float(np.polyfit(steps[after], rss[after], 1)[0]) * 1e5 if after.sum() >= 2 else float("nan")
    half = steps >= steps[-1] / 2
    half_slope = float(np.polyfit(steps[half], rss[half], 1)[0]) * 1e5 if half.sum() >= 2 else float("nan")
    return {
        "initial": float(rss[0]),
        "start_step": int(steps[start_index]),
        "start": float(rss[start_index]),
        "max": float(rss.max()),
        "max_after": float(rss[after].max()),
        "end": float(rss[-1]),
        "half_start_step": int(steps[half][0]),
        "half_slope": half_slope,
        "half_growth": float(rss[-1] - rss[half][0]),
        "slope": slope,
        "growth": float(rss[-1] - rss[start_index]),
    }


def plot_memory(curves: list[tuple[str, list[tuple[int, float]], int]], path: Path, title: str) -> None:
    """Plot RSS against steps.

    :param curves: ``(label, samples, warm-up end step)`` per run; the warm-up end is marked.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.0), dpi=120)
    everything = []
    for (label, samples, warmup), color in zip(curves, ("tab:blue", "tab:orange")):
        steps = np.array([s for s, _ in samples], dtype=float)
        rss = np.array([r for _, r in samples])
        everything.append(rss)
        ax.plot(steps / 1e3, rss, marker=".", ms=3, lw=1, color=color, label=label)
        ax.axvline(warmup / 1e3, color=color, ls="--", lw=0.8, alpha=0.7)
    rss = np.concatenate(everything)
    ax.set_xlabel("env steps (thousands); dashed: end of warm-up")
    ax.set_ylabel("process RSS (MiB)")
    ax.set_title(title, fontsize=10)
    lo, hi = rss.min(), rss.max()
    ax.set_ylim(max(0.0, lo - max(20.0, 0.1 * lo)), hi + max(20.0, 0.1 * hi))
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------------------ report
def _trim_rows(soak: SoakResult, mem: dict) -> list[str]:
    if soak.rss_after_trim is None:
        return ["| RSS at end after glibc `malloc_trim(0)` | n/a |"]
    grew = "yes" if soak.rss_after_trim > mem["start"] else "no"
    return [
        f"| RSS at end after glibc `malloc_trim(0)` (free heap pages handed back) | {soak.rss_after_trim:.1f} MiB |",
        f"| memory in use grew after warm-up (RSS after trim at end > RSS at start) | **{grew}** |",
    ]


def report(
    args,
    fuzz: FuzzResult | None,
    soak: SoakResult | None,
    control: SoakResult | None,
    warnings: Counter,
    command: str,
) -> str:
    tunables = [f"{k}={v}" for k, v in sorted(os.environ.items()) if k.startswith("MALLOC_")]
    lines = [
        "# Reliability: morphology fuzz and multi-task memory soak",
        "",
        f"Command: `{command}`  ",
        f"Machine: {MACHINE} ({platform.machine()}, Linux, Python {platform.python_version()}, "
        f"mujoco {mujoco.__version__}, gymnasium {gym.__version__}, numpy {np.__version__}); one process; "
        f"date {date.today().isoformat()}  ",
        "Allocator: glibc malloc, " + (", ".join(tunables) or "default tunables"),
        "",
    ]
    if fuzz is not None:
        clean_pct = 100.0 * fuzz.clean / max(fuzz.count, 1)
        lines += [
            "## Fuzz: generated morphologies on Unimal-FT-v0",
            "",
            f"Seeds {args.fuzz_seed}..{args.fuzz_seed + fuzz.count - 1} -> `generate_unimal(seed)` -> MJCF file "
            f"(unimals_100 layout, temporary directory) -> `load_morphology` -> "
            f'`gym.make("Unimal-FT-v0", morphologies=[path])`, reset(seed=seed), {args.fuzz_steps} uniform random '
            "actions in [-1, 1] (reset on episode end). Checked on every reset and step: observation keys, shapes, "
            "dtype float32, values finite and inside the space's bounds; reward finite.",
            "",
            "| measure | value |",
            "|---|---|",
            f"| robots generated | {fuzz.generated} / {fuzz.count} |",
            f"| loaded and compiled into an FT world | {fuzz.compiled} / {fuzz.count} |",
            f"| ran {args.fuzz_steps} steps clean | **{fuzz.clean} / {fuzz.count}** ({clean_pct:.1f} %) |",
            f"| failures | {len(fuzz.failures)} |",
            f"| env steps / episodes | {fuzz.steps:,} / {fuzz.episodes:,} |",
            f'| physics faults (`info["physics_fault"]`, the episode ended cleanly) | {fuzz.physics_faults} |',
            f"| limbs per robot (count:robots) | {' '.join(f'{k}:{v}' for k, v in sorted(fuzz.limbs.items()))} |",
            f"| time | {fuzz.seconds:.0f} s ({fuzz.generate_seconds:.0f} s of it generating; "
            f"{1e3 * fuzz.seconds / max(fuzz.count, 1):.0f} ms per robot) |",
            "",
        ]
        if fuzz.failures:
            lines += ["Failures:", "", "| seed | stage | error |", "|---|---|---|"]
            lines += [f"| {s} | {stage} | {err.replace('|', '/')} |" for s, stage, err in fuzz.failures[:50]]
            if len(fuzz.failures) > 50:
                lines.append(f"| ... | | {len(fuzz.failures) - 50} more |")
            lines.append("")
        else:
            lines += ["No failures.", ""]
    if soak is not None:
        warmup = warmup_end(soak, args.warmup_steps)
        mem = memory_summary(soak.samples, warmup)
        rate = soak.steps / soak.seconds
        evicting = args.world_cache_size < args.soak_morphologies
        full = (
            f"step {soak.caches_full_at:,}"
            if soak.caches_full_at is not None
            else "not reached within the soak, so only the minimum applies"
        )
        flat = "yes" if abs(mem["slope"]) < 1.0 else "no"
        lines += [
            "## Soak: all 10 tasks, random actions",
            "",
            f"{soak.steps:,} env steps round-robin over the 10 tasks (`Unimal-<task>-v0` from `gym.make`), "
            f"chunks of {args.chunk} steps per task, every env on the first {args.soak_morphologies} robots of the "
            f"shipped train set (world cache {args.world_cache_size} per env"
            + (", so worlds keep being evicted and recompiled" if evicting else "")
            + f": {soak.compiled_worlds} world compilations in all), uniform random actions, reset on episode end. "
            f"RSS sampled every {args.sample_every:,} steps. Warm-up = at least {args.warmup_steps:,} steps and until "
            f"every env's world cache is full ({full}), i.e. the first {mem['start_step']:,} steps: before that, "
            "memory grows by design as the caches fill.",
            "",
            "| measure | value |",
            "|---|---|",
            f"| env steps / episodes | {soak.steps:,} / {soak.episodes:,} |",
            f"| steps/s (whole soak: steps, checks, resets, world compiles) | {rate:,.0f} |",
            f"| time | {soak.seconds:.0f} s |",
            f"| non-finite observations or rewards | **{soak.non_finite}** |",
            f"| observations outside the space after reset | {soak.bad_observations} |",
            f'| physics faults (`info["physics_fault"]`) | {soak.physics_faults} |',
            f"| RSS before creating the envs | {soak.rss_before_envs:.1f} MiB |",
            f"| RSS after creating and resetting the 10 envs (step 0) | {mem['initial']:.1f} MiB |",
            f"| RSS at start (after warm-up, step {mem['start_step']:,}) | {mem['start']:.1f} MiB |",
            f"| RSS max (whole soak / after warm-up) | {mem['max']:.1f} / {mem['max_after']:.1f} MiB |",
            f"| RSS at end | {mem['end']:.1f} MiB |",
            f"| growth after warm-up (end - start) | {mem['growth']:+.1f} MiB |",
            f"| slope after warm-up (least squares) | **{mem['slope']:+.3f} MiB per 100k steps** |",
            f"| raw RSS flat (abs(slope after warm-up) < 1 MiB per 100k steps) | {flat} |",
            f"| second half only (steps {mem['half_start_step']:,}-{soak.steps:,}): growth / slope | "
            f"{mem['half_growth']:+.1f} MiB / {mem['half_slope']:+.3f} MiB per 100k steps |",
            *_trim_rows(soak, mem),
            "",
            "![RSS vs steps](reliability_memory.png)",
            "",
            "RSS samples (thousand steps: MiB): " + ", ".join(f"{s // 1000}: {r:.0f}" for s, r in soak.samples),
            "",
            "Per task:",
            "",
            "| task | steps | episodes | physics faults | world compilations |",
            "|---|---|---|---|---|",
        ]
        for task, stats in soak.per_task.items():
            counts = (stats["steps"], stats["episodes"], stats["physics_faults"], stats["worlds"])
            lines.append(f"| {task} | " + " | ".join(f"{n:,}" for n in counts) + " |")
        lines.append("")
        if soak.first_problems:
            lines += ["First non-finite values:", "", *[f"- {p}" for p in soak.first_problems], ""]
    if control is not None:
        c_mem = memory_summary(control.samples, warmup_end(control, args.warmup_steps))
        c_full = f"at step {control.caches_full_at:,}" if control.caches_full_at is not None else "not reached"
        lines += [
            "### Control: the same soak without evictions",
            "",
            f"The same soak for {control.steps:,} steps in a fresh (spawned) process, with a world cache of "
            f"{args.soak_morphologies} >= {args.soak_morphologies} robots: every world is compiled once and never "
            f"evicted ({control.compiled_worlds} compilations; every cache full: {c_full}). Warm-up as above, "
            f"i.e. the first {c_mem['start_step']:,} steps. If this curve is flat while the soak above grows in steps, "
            "the growth comes from replacing compiled worlds (the allocator reusing freed MjModel/MjData memory), "
            "not from stepping, resetting or observing; `malloc_trim` separates retained free heap from live memory.",
            "",
            "| measure | value |",
            "|---|---|",
            f"| env steps / episodes / steps/s | {control.steps:,} / {control.episodes:,} / {control.steps / control.seconds:,.0f} |",
            f"| non-finite observations or rewards / physics faults | **{control.non_finite}** / {control.physics_faults} |",
            f"| RSS at step 0 / at start (after warm-up, step {c_mem['start_step']:,}) | {c_mem['initial']:.1f} / "
            f"{c_mem['start']:.1f} MiB |",
            f"| RSS max after warm-up / at end | {c_mem['max_after']:.1f} / {c_mem['end']:.1f} MiB |",
            f"| growth after warm-up / slope | {c_mem['growth']:+.1f} MiB / **{c_mem['slope']:+.3f} MiB per 100k steps** |",
            *_trim_rows(control, c_mem),
            "",
            "RSS samples (thousand steps: MiB): " + ", ".join(f"{s // 1000}: {r:.0f}" for s, r in control.samples),
            "",
        ]
    lines += ["## MuJoCo warnings", ""]
    if warnings:
        lines += ["| count | warning |", "|---|---|"]
        lines += [f"| {n} | {msg} |" for msg, n in warnings.most_common(20)]
    else:
        lines.append("None.")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fuzz-count", type=int, default=1000, help="generated robots to fuzz (0 = skip the fuzz)")
    parser.add_argument("--fuzz-seed", type=int, default=0, help="first generator seed of the fuzz")
    parser.add_argument("--fuzz-steps", type=int, default=200, help="random-action steps per fuzzed robot")
    parser.add_argument("--soak-steps", type=int, default=1_000_000, help="env steps of the soak (0 = skip it)")
    parser.add_argument("--soak-morphologies", type=int, default=20, help="train robots per soak env")
    parser.add_argument("--chunk", type=int, default=1000, help="steps per task before moving to the next")
    parser.add_argument("--sample-every", type=int, default=10_000, help="RSS sampling period in steps")
    parser.add_argument(
        "--warmup-steps", type=int, default=100_000,
        help="minimum steps before the memory baseline (it also waits for every world cache to be full)",
    )  # fmt: skip
    parser.add_argument(
        "--control-steps", type=int, default=400_000,
        help="steps of the no-eviction control soak in a fresh process (0 = skip it)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="seed of the soak's envs and actions")
    parser.add_argument(
        "--world-cache-size", type=int, default=16,
        help="compiled worlds each soak env keeps (env default 16; >= --soak-morphologies means no eviction)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=RESULTS, help="markdown report")
    parser.add_argument("--plot", type=Path, default=PLOT, help="RSS-vs-steps PNG")
    args = parser.parse_args(argv)
    shown = sys.argv[1:] if argv is None else argv
    command = "python benchmarks/reliability.py" + ("" if not shown else " " + shlex.join(shown))

    fuzz = soak = control = None
    with MujocoWarnings() as warnings:
        if args.fuzz_count > 0:
            fuzz = run_fuzz(args.fuzz_count, args.fuzz_seed, args.fuzz_steps)
            print(
                f"fuzz: {fuzz.compiled}/{fuzz.count} compiled, {fuzz.clean}/{fuzz.count} clean, "
                f"{len(fuzz.failures)} failures, {fuzz.physics_faults} physics faults, {fuzz.seconds:.0f} s"
            )
            for seed, stage, err in fuzz.failures[:10]:
                print(f"  seed {seed} [{stage}]: {err}")
        if args.soak_steps > 0:
            soak = run_soak(args.soak_steps, args.soak_morphologies, args.chunk, args.sample_every, args.seed, args.world_cache_size)
            warmup = warmup_end(soak, args.warmup_steps)
            mem = memory_summary(soak.samples, warmup)
            print(
                f"soak: {soak.steps:,} steps in {soak.seconds:.0f} s ({soak.steps / soak.seconds:,.0f} steps/s), "
                f"non-finite {soak.non_finite}, physics faults {soak.physics_faults}; RSS start {mem['start']:.1f} "
                f"max {mem['max']:.1f} end {mem['end']:.1f} MiB, slope {mem['slope']:+.3f} MiB/100k steps"
            )
            label = f"soak: world cache {args.world_cache_size}, {args.soak_morphologies} robots"
            curves = [(label, soak.samples, warmup)]
            if args.control_steps > 0:
                control = run_soak_in_fresh_process(
                    args.control_steps, args.soak_morphologies, args.chunk, args.sample_every, args.seed,
                    args.soak_morphologies, "control soak (no eviction)",
                )  # fmt: skip
                c_warmup = warmup_end(control, args.warmup_steps)
                c_mem = memory_summary(control.samples, c_warmup)
                print(
                    f"control: {control.steps:,} steps, non-finite {control.non_finite}, RSS start "
                    f"{c_mem['start']:.1f} end {c_mem['end']:.1f} MiB, slope {c_mem['slope']:+.3f} MiB/100k steps"
                )
                curves.append(("control: no eviction (fresh process)", control.samples, c_warmup))
            plot_memory(curves, args.plot, f"UNIMAL soak over 10 tasks, {args.soak_morphologies} robots ({MACHINE})")
    for run in (soak, control):
        if run is not None:
            warnings.messages.update(run.warnings)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(report(args, fuzz, soak, control, warnings.messages, command))
    print(f"wrote {args.out}" + (f" and {args.plot}" if soak is not None else ""))
    failed = (fuzz is not None and fuzz.failures) or any(r is not None and r.non_finite for r in (soak, control))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
