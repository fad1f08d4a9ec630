"""Cost of DivMorph vs MetaMorph at equal size: PPO-update time and parameter counts.

Both policies are timed side by side in one process on the same batch: each repeat runs one
PPO-style update step (``evaluate_actions`` + loss + backward, train mode) of every policy, in
alternating order, and the table reports medians and their ratio. A rollout step (``forward`` in
eval mode without autograd, one observation per env) is timed the same way.

    python benchmarks/policy_cost.py                      # small + paper, 1 and 2 threads, minibatch 256 and 512
    python benchmarks/policy_cost.py --sizes small --threads 1 --batch 256 --repeats 5 --output /tmp/x.md
    python benchmarks/policy_cost.py --sizes small --processes 3   # each cell in 3 fresh processes

Run on an idle machine. On a small VM the time of memory-bound operations (ReLU, copies of the
(tokens x ff_dim) activations) varies by several percent from one process to the next, with its
memory layout; ``--processes N`` repeats the whole measurement in N fresh processes and reports
the median over processes of each cell's time and ratio (and every process's ratio).

Target (deployment issue): a DivMorph update costs at most 1.2x MetaMorph's in every cell of the
grid (threads x minibatch) at the small size.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch as th

from sb3_divmorph import DivMorphPolicy, MetaMorphPolicy
from sb3_divmorph.testing import random_observations
from unimal_envs import contract

#: name -> (class, extra policy kwargs); ratios are taken against the first entry.
POLICIES = {
    "MetaMorph": (MetaMorphPolicy, {}),
    "DivMorph": (DivMorphPolicy, {}),
    "DivMorph+critic": (DivMorphPolicy, {"factorize_critic": True}),
}


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _sync(device: th.device) -> None:
    if device.type == "cuda":
        th.cuda.synchronize(device)


def update_step(policy, obs, actions) -> None:
    """One PPO minibatch step without the optimizer update (forward + backward)."""
    values, log_prob, entropy = policy.evaluate_actions(obs, actions)
    loss = -log_prob.mean() + 0.5 * values.pow(2).mean() - 0.0 * entropy.mean()
    policy.optimizer.zero_grad(set_to_none=True)
    loss.backward()


def rollout_step(policy, obs) -> None:
    with th.no_grad():
        policy(obs)


def time_interleaved(policies: dict, step, repeats: int, warmup: int, device: th.device) -> dict[str, list[float]]:
    """Run ``step(policy)`` for every policy per repeat, alternating the order; seconds per call."""
    times: dict[str, list[float]] = {name: [] for name in policies}
    names = list(policies)
    for rep in range(warmup + repeats):
        for name in names if rep % 2 == 0 else names[::-1]:
            _sync(device)
            start = time.perf_counter()
            step(policies[name])
            _sync(device)
            if rep >= warmup:
                times[name].append(time.perf_counter() - start)
    return times


#: the largest DivMorph / MetaMorph update-time ratio accepted in any cell
TARGET = 1.2


def benchmark_size(args: argparse.Namespace, preset: str, device: th.device, batch: int):
    n_envs, repeats, warmup, seed = args.n_envs, args.repeats, args.warmup, args.seed
    space, action_space = contract.observation_space(), contract.action_space()
    policies = {}
    for name, (cls, kwargs) in POLICIES.items():
        th.manual_seed(seed)
        policies[name] = cls(space, action_space, lambda _: 3e-4, preset=preset, **kwargs).to(device)

    obs_np = random_observations(space, batch, seed=seed, n_morphologies=args.morphologies, n_tasks=args.tasks)
    some = next(iter(policies.values()))
    obs, _ = some.obs_to_tensor(obs_np)
    uniform = np.random.default_rng(seed).uniform(-1, 1, (batch, action_space.shape[0]))
    actions = th.as_tensor(uniform, dtype=th.float32, device=device)
    for policy in policies.values():
        policy.set_training_mode(True)
    update = time_interleaved(policies, lambda p: update_step(p, obs, actions), repeats, warmup, device)

    rollout_obs, _ = some.obs_to_tensor(random_observations(space, n_envs, seed=seed + 1, n_tasks=1))
    for policy in policies.values():
        policy.set_training_mode(False)
    rollout = time_interleaved(policies, lambda p: rollout_step(p, rollout_obs), 5 * repeats, warmup, device)
    counts = {name: policy.parameter_counts() for name, policy in policies.items()}
    return update, rollout, counts, policies["DivMorph"].config


def _ms(values: list[float]) -> float:
    return 1000 * statistics.median(values)


def _over_processes(runs: list[dict[str, list[float]]], name: str, base: str) -> tuple[float, float, list[float]]:
    """Median over processes of one policy's median time (ms) and of its per-process ratio to ``base``."""
    times = [_ms(run[name]) for run in runs]
    ratios = [_ms(run[name]) / _ms(run[base]) for run in runs]
    return statistics.median(times), statistics.median(ratios), ratios


def render(results: dict, args: argparse.Namespace, device: th.device) -> str:
    """Markdown table of ``results[(size, threads, batch)] = (update runs, rollout runs, counts, config)``,
    where each ``runs`` holds one ``{policy: [seconds]}`` per process."""
    names = list(POLICIES)
    base = names[0]
    processes = len(next(iter(results.values()))[0])
    lines = [
        "# Policy cost: DivMorph vs MetaMorph at equal size",
        "",
        f"Command: `{' '.join(['python', *sys.argv])}`",
        "",
        f"Machine: {_cpu_name()} ({os.cpu_count()} cores, load average {args.load:.2f} at start), "
        f"{platform.system()} {platform.machine()}, device `{device}`"
        + (f" ({th.cuda.get_device_name(device)})" if device.type == "cuda" else "")
        + f", torch {th.__version__}; "
        f"{datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')}.",
        "",
        f"Update step = `evaluate_actions` + loss + backward on a minibatch of B observations "
        f"of {args.morphologies} robots x {args.tasks} tasks (train mode; actor and critic). Rollout step = "
        f"`forward` under `no_grad` in eval mode on {args.n_envs} observations. All policies are timed in "
        f"the same process, interleaved in alternating order ({args.repeats} update repeats, "
        f"{5 * args.repeats} rollout repeats, {args.warmup} warm-up); medians"
        + (
            f", then the median over {processes} fresh processes of each cell's time and ratio "
            f"(every process's DivMorph update ratio in the last column). "
            if processes > 1
            else ". "
        )
        + "`DivMorph` is the default policy (diverted actor, MetaMorph critic); `DivMorph+critic` also "
        f"factorizes and gates the critic (`factorize_critic=True`). Target: DivMorph update <= {TARGET}x "
        "MetaMorph's in every cell at the small size.",
        "",
        "## Time (ms, median; ratio to MetaMorph)",
        "",
        "| size | threads | minibatch B | "
        + " | ".join(f"{n} update" for n in names)
        + " | "
        + " | ".join(f"{n} rollout" for n in names)
        + " | target |"
        + (" DivMorph update ratio per process |" if processes > 1 else ""),
        "|---|---|---|" + "---:|" * (2 * len(names)) + "---|" + ("---|" if processes > 1 else ""),
    ]
    for (size, threads, batch), (update, rollout, _, _) in results.items():
        cells = []
        for runs in (update, rollout):
            for n in names:
                value, ratio, _ = _over_processes(runs, n, base)
                cells.append(f"{value:.1f}" if n == base else f"{value:.1f} (**{ratio:.2f}x**)")
        _, ratio, per_process = _over_processes(update, "DivMorph", base)
        verdict = ("met" if ratio <= TARGET else "not met") if size == "small" else "-"
        spread = (" " + ", ".join(f"{r:.2f}" for r in per_process) + " |") if processes > 1 else ""
        lines.append(f"| {size} | {threads} | {batch} | " + " | ".join(cells) + f" | {verdict} |" + spread)
    lines += ["", "## Parameters (stored elements per part)", ""]
    shown: set[str] = set()
    for (size, _, _), (_, _, counts, config) in results.items():
        if size in shown:
            continue
        shown.add(size)
        keys = sorted(set().union(*(counts[n] for n in names)), key=lambda k: (k == "total", k))
        lines += [
            f"### {size}",
            "",
            "DivMorph: "
            + ", ".join(
                f"{k}={config[k]}"
                for k in ("d_model", "n_layers", "n_heads", "ff_dim") + ("n_morph_tailors", "n_task_tailors", "top_k_morph", "top_k_task")
            ),
            "",
            "| part | " + " | ".join(names) + " |",
            "|---|" + "---:|" * len(names),
        ]
        for key in keys:
            ref = counts[base].get(key, 0)
            cells = []
            for n in names:
                value = counts[n].get(key, 0)
                cells.append(f"{value:,}" if n == base or not ref else f"{value:,} ({value / ref:.2f}x)")
            lines.append(f"| {key} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "Notes: a factorized layer stores `U`, `V` and `s` (an `r x r` one about twice a dense square "
        "matrix); the Cayley-parametrized square factor counts as its `r(r-1)/2` free skew entries plus "
        "its `r x r` SVD base (a buffer the student needs at inference). `router/*` (morphology encoder "
        "and both gates) exists only in DivMorph.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["small", "paper"], choices=sorted(MetaMorphPolicy.preset_table))
    parser.add_argument("--batch", type=int, nargs="+", default=[256, 512], help="minibatch sizes of the update step")
    parser.add_argument("--n-envs", type=int, default=4, help="batch of the rollout step")
    parser.add_argument("--morphologies", type=int, default=32, help="distinct robots in the minibatch")
    parser.add_argument("--tasks", type=int, default=5, help="distinct tasks in the minibatch")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch CPU thread counts")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="results/policy_cost.md")
    parser.add_argument("--processes", type=int, default=1, help="repeat the measurement in N fresh processes (median over them)")
    parser.add_argument("--json", help=argparse.SUPPRESS)  # a child process writes its raw timings here
    args = parser.parse_args(argv)

    args.load = os.getloadavg()[0]
    if args.device == "auto":
        args.device = "cuda" if th.cuda.is_available() else "cpu"
    device = th.device(args.device)
    if args.processes > 1:
        results = _measure_in_processes(args)
    else:
        results = {}
        for size in args.sizes:
            for threads in args.threads:
                th.set_num_threads(threads)
                for batch in args.batch:
                    update, rollout, counts, config = benchmark_size(args, size, device, batch)
                    results[size, threads, batch] = ([update], [rollout], counts, config)
                    print(
                        f"{size}, {threads} thread(s), B={batch}: update " + ", ".join(f"{n} {_ms(t):.1f} ms" for n, t in update.items()),
                        flush=True,
                    )
    if args.json:
        cells = [
            {"cell": list(key), "update": u[0], "rollout": r[0], "counts": c, "config": cfg} for key, (u, r, c, cfg) in results.items()
        ]
        Path(args.json).write_text(json.dumps(cells))
        return
    text = render(results, args, device)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(text)
    print(text)


def _measure_in_processes(args: argparse.Namespace) -> dict:
    """Run the whole measurement in ``args.processes`` fresh processes, one after the other; gather them."""
    child = [
        sys.executable,
        __file__,
        "--sizes",
        *args.sizes,
        "--batch",
        *map(str, args.batch),
        "--threads",
        *map(str, args.threads),
        "--n-envs",
        str(args.n_envs),
        "--morphologies",
        str(args.morphologies),
        "--tasks",
        str(args.tasks),
        "--repeats",
        str(args.repeats),
        "--warmup",
        str(args.warmup),
        "--device",
        args.device,
        "--seed",
        str(args.seed),
    ]
    results: dict = {}
    with tempfile.TemporaryDirectory() as folder:
        for process in range(args.processes):
            out = Path(folder) / f"process-{process}.json"
            print(f"process {process + 1}/{args.processes}", flush=True)
            subprocess.run([*child, "--json", str(out)], check=True)
            for cell in json.loads(out.read_text()):
                update, rollout, _, _ = results.setdefault(tuple(cell["cell"]), ([], [], cell["counts"], cell["config"]))
                update.append(cell["update"])
                rollout.append(cell["rollout"])
    return results


if __name__ == "__main__":
    main()
