"""Cost of DivMorph vs MetaMorph at equal size: PPO-update time and parameter counts.

Both policies are timed side by side in one process on the same batch: each repeat runs one
PPO-style update step (``evaluate_actions`` + loss + backward, train mode) of every policy, in
alternating order, and the table reports medians and their ratio. A rollout step (``forward`` in
eval mode without autograd, one observation per env) is timed the same way.

    python benchmarks/policy_cost.py                      # default + paper sizes, 1 thread
    python benchmarks/policy_cost.py --sizes small --repeats 5 --output /tmp/x.md
"""

from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch as th

from sb3_divmorph import DivMorphPolicy, MetaMorphPolicy
from sb3_divmorph.testing import random_observations
from unimal_envs import contract

POLICIES = {"MetaMorph": MetaMorphPolicy, "DivMorph": DivMorphPolicy}


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


def benchmark_size(preset: str, batch: int, n_envs: int, repeats: int, warmup: int, device: th.device, seed: int):
    space, action_space = contract.observation_space(), contract.action_space()
    policies = {}
    for name, cls in POLICIES.items():
        th.manual_seed(seed)
        policies[name] = cls(space, action_space, lambda _: 3e-4, preset=preset).to(device)

    obs_np = random_observations(space, batch, seed=seed)
    some = next(iter(policies.values()))
    obs, _ = some.obs_to_tensor(obs_np)
    actions = th.as_tensor(np.random.default_rng(seed).uniform(-1, 1, (batch, action_space.shape[0])), dtype=th.float32, device=device)
    for policy in policies.values():
        policy.set_training_mode(True)
    update = time_interleaved(policies, lambda p: update_step(p, obs, actions), repeats, warmup, device)

    rollout_obs, _ = some.obs_to_tensor(random_observations(space, n_envs, seed=seed + 1))
    for policy in policies.values():
        policy.set_training_mode(False)
    rollout = time_interleaved(policies, lambda p: rollout_step(p, rollout_obs), 5 * repeats, warmup, device)
    counts = {name: policy.parameter_counts() for name, policy in policies.items()}
    return update, rollout, counts, policies["DivMorph"].config


def _ms(values: list[float]) -> float:
    return 1000 * statistics.median(values)


def render(results: dict, args: argparse.Namespace, device: th.device) -> str:
    lines = [
        "# Policy cost: DivMorph vs MetaMorph at equal size",
        "",
        f"Command: `{' '.join(['python', *sys.argv])}`",
        "",
        f"Machine: {_cpu_name()}, {platform.system()} {platform.machine()}, device `{device}`"
        + (f" ({th.cuda.get_device_name(device)})" if device.type == "cuda" else "")
        + f", torch {th.__version__}, {th.get_num_threads()} torch thread(s); "
        f"{datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')}.",
        "",
        f"Update step = `evaluate_actions` + loss + backward on a minibatch of {args.batch} observations "
        f"(train mode; actor and critic); rollout step = `forward` under `no_grad` in eval mode on "
        f"{args.n_envs} observations. Both policies are timed in the same process, interleaved "
        f"({args.repeats} update repeats, {5 * args.repeats} rollout repeats, {args.warmup} warm-up), "
        "medians reported. Target: DivMorph <= 1.3x MetaMorph.",
        "",
        "## Time",
        "",
        "| size | MetaMorph update (ms) | DivMorph update (ms) | ratio | MetaMorph rollout (ms) | DivMorph rollout (ms) | ratio |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for size, (update, rollout, _, _) in results.items():
        mu, du = _ms(update["MetaMorph"]), _ms(update["DivMorph"])
        mr, dr = _ms(rollout["MetaMorph"]), _ms(rollout["DivMorph"])
        lines.append(f"| {size} | {mu:.1f} | {du:.1f} | **{du / mu:.2f}x** | {mr:.2f} | {dr:.2f} | {dr / mr:.2f}x |")
    lines += ["", "## Parameters (stored elements per part)", ""]
    for size, (_, _, counts, config) in results.items():
        keys = sorted(set(counts["MetaMorph"]) | set(counts["DivMorph"]), key=lambda k: (k == "total", k))
        lines += [
            f"### {size}",
            "",
            "DivMorph: "
            + ", ".join(f"{k}={config[k]}" for k in ("d_model", "n_layers", "n_heads", "ff_dim", "n_morph_tailors", "n_task_tailors", "top_k_morph", "top_k_task")),
            "",
            "| part | MetaMorph | DivMorph | ratio |",
            "|---|---:|---:|---:|",
        ]
        for key in keys:
            m, d = counts["MetaMorph"].get(key, 0), counts["DivMorph"].get(key, 0)
            ratio = f"{d / m:.2f}x" if m else "-"
            lines.append(f"| {key} | {m:,} | {d:,} | {ratio} |")
        lines.append("")
    lines += [
        "Notes: a factorized `r x r` layer stores `U`, `V`, `s` (about twice a dense square matrix); the "
        "Cayley-parametrized square factor is counted as its `r(r-1)/2` free skew entries (its SVD base "
        "is a buffer). `router/*` exists only in DivMorph and is shared by actor and critic.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["small", "paper"], choices=sorted(MetaMorphPolicy.preset_table))
    parser.add_argument("--batch", type=int, default=512, help="minibatch size of the update step")
    parser.add_argument("--n-envs", type=int, default=4, help="batch of the rollout step")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="results/policy_cost.md")
    args = parser.parse_args(argv)

    th.set_num_threads(args.threads)
    device = th.device("cuda" if args.device == "auto" and th.cuda.is_available() else ("cpu" if args.device == "auto" else args.device))
    results = {}
    for size in args.sizes:
        results[size] = benchmark_size(size, args.batch, args.n_envs, args.repeats, args.warmup, device, args.seed)
        update = results[size][0]
        print(
            f"{size}: update MetaMorph {_ms(update['MetaMorph']):.1f} ms, DivMorph {_ms(update['DivMorph']):.1f} ms, "
            f"ratio {_ms(update['DivMorph']) / _ms(update['MetaMorph']):.2f}",
            flush=True,
        )
    text = render(results, args, device)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
