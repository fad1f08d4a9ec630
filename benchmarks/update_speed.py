"""Speed of the PPO update: token packing, bfloat16, minibatch size and torch.compile, each checked against the float32 padded update.

The update is what a GPU run spends most of its time in (72% of the paper-size MetaMorph's PPO on an
H200, ``results/gpu-h200``). This benchmark times SB3's update as PPO runs it -- ``evaluate_actions``,
the clipped surrogate, value and entropy losses, backward, gradient clipping and one Adam step per
minibatch -- over one epoch of a fixed buffer, for each option against the baseline in the same
process (interleaved, medians), and checks what each option changes:

* ``packed``: the Transformer's projections and FFNs on the real tokens only (the default since
  this benchmark; :class:`~sb3_divmorph.nn.transformer.TokenPacking`); the loss and gradients of one
  minibatch against the padded pass's (max relative gradient difference; exact up to rounding).
* ``bf16``: the policy's ``mixed_precision=True`` (bfloat16 autocast in the embedding, encoders and
  Transformer); the gradient's cosine to float32's (``results/mixed_precision.md`` has the rest).
* minibatch size (``--batches``): the per-sample cost at each size; a larger minibatch takes fewer
  optimiser steps per epoch, so it needs the learning rate chosen again (see the GPU ledger).
* ``--compile``: ``torch.compile`` of ``evaluate_actions`` (first call's compile time reported apart).

Buffers are built from reset observations of real robots (the official training robots when
fetched, else the shipped generated set), so the share of padded token slots is the robots' own
(8.6 real of 12 on the official set). Run on an idle machine, one thread per process:

    python benchmarks/update_speed.py                          # small + paper, MetaMorph + DivMorph
    python benchmarks/update_speed.py --presets paper --device cuda --batches 2048 8192 --samples 65536
"""

from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from torch.nn import functional as F

from sb3_divmorph import DivMorphPolicy, MetaMorphPolicy
from sb3_divmorph.nn.transformer import TransformerEncoder
from unimal_envs import contract
from unimal_envs.morphology import morphology_files

POLICIES = {"MetaMorph": MetaMorphPolicy, "DivMorph": DivMorphPolicy}


def robot_observations(n_robots: int, seed: int) -> tuple[dict[str, np.ndarray], str]:
    """One reset observation per robot (FT), the official training robots when fetched."""
    try:
        robots, name = morphology_files("unimals100-train")[:n_robots], "unimals100-train"
    except Exception:  # noqa: BLE001 -- not fetched on this machine
        robots, name = morphology_files("train")[:n_robots], "train (generated)"
    env = gym.make("Unimal-FT-v0", morphologies=robots)
    rows = [env.reset(seed=seed + i, options={"morphology": robot.stem})[0] for i, robot in enumerate(robots)]
    env.close()
    return {key: np.stack([row[key] for row in rows]) for key in rows[0]}, f"{len(robots)} robots of {name}"


def make_buffer(pool: dict[str, np.ndarray], samples: int, seed: int) -> dict[str, np.ndarray]:
    """``samples`` observations drawn from the robots' pool, their proprioception jittered."""
    rng = np.random.default_rng(seed)
    pick = rng.integers(len(pool["proprioceptive"]), size=samples)
    buffer = {key: value[pick].copy() for key, value in pool.items()}
    real = buffer["obs_padding_mask"][..., None] < 0.5
    buffer["proprioceptive"] += np.where(real, rng.normal(0, 0.1, buffer["proprioceptive"].shape), 0).astype(np.float32)
    return buffer


class Update:
    """One configuration's PPO epoch over a fixed buffer (SB3's loss, clipping and Adam step)."""

    def __init__(self, cls, preset: str, pack: bool, bf16: bool, compile_: bool, buffer, device: th.device, seed: int):
        th.manual_seed(seed)
        self.policy = cls(contract.observation_space(), contract.action_space(), lambda _: 3e-4, preset=preset, mixed_precision=bf16).to(
            device
        )
        for encoder in (m for m in self.policy.modules() if isinstance(m, TransformerEncoder)):
            encoder.pack_tokens = pack
        self.policy.set_training_mode(True)
        self.obs = {key: th.as_tensor(value, device=device) for key, value in buffer.items()}
        samples = len(buffer["proprioceptive"])
        generator = np.random.default_rng(seed)
        self.actions = th.as_tensor(generator.uniform(-1, 1, (samples, contract.action_space().shape[0])), dtype=th.float32, device=device)
        self.advantages = th.as_tensor(generator.normal(size=samples), dtype=th.float32, device=device)
        self.returns = th.as_tensor(generator.normal(size=samples), dtype=th.float32, device=device)
        with th.no_grad():
            _, self.old_log_prob, _ = self.policy.evaluate_actions(self.obs_slice(slice(0, samples)), self.actions)
        self.evaluate = th.compile(self.policy.evaluate_actions) if compile_ else self.policy.evaluate_actions
        # The timing repeats epochs over one buffer: a policy that moved would drift off the buffer's
        # log-probabilities until the ratios overflow. Adam's step costs the same at rate 0.
        for group in self.policy.optimizer.param_groups:
            group["lr"] = 0.0
        self.device = device

    def obs_slice(self, index) -> dict[str, th.Tensor]:
        return {key: value[index] for key, value in self.obs.items()}

    def loss(self, index) -> th.Tensor:
        values, log_prob, entropy = self.evaluate(self.obs_slice(index), self.actions[index])
        ratio = th.exp(log_prob - self.old_log_prob[index])
        advantages = self.advantages[index]
        policy_loss = -th.min(advantages * ratio, advantages * th.clamp(ratio, 0.8, 1.2)).mean()
        return policy_loss + 0.5 * F.mse_loss(self.returns[index], values.flatten()) - 0.0 * entropy.mean()

    def gradient(self, index) -> th.Tensor:
        """The flat gradient of one minibatch's loss (no step)."""
        self.policy.optimizer.zero_grad(set_to_none=True)
        self.loss(index).backward()
        return th.cat([p.grad.flatten() for p in self.policy.parameters() if p.grad is not None]).float()

    def epoch(self, batch: int) -> None:
        for start in range(0, len(self.actions), batch):
            index = slice(start, start + batch)
            self.policy.optimizer.zero_grad(set_to_none=True)
            self.loss(index).backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), 0.5)
            self.policy.optimizer.step()
        if self.device.type == "cuda":
            th.cuda.synchronize(self.device)


def measure(args: argparse.Namespace, device: th.device, results: list[dict]) -> None:
    """Appends to ``results`` the buffer's description, then one row per option and minibatch as it is
    measured (so that an interrupted run still reports what it measured)."""
    pool, robots = robot_observations(args.robots, args.seed)
    real = float((pool["obs_padding_mask"] < 0.5).sum(1).mean())
    results.append(dict(robots=robots, real_tokens=real))
    buffer = make_buffer(pool, args.samples, args.seed)
    configs = [("padded", False, False, False), ("packed", True, False, False), ("packed+bf16", True, True, False)]
    if args.compile:
        configs.append(("packed+compile", True, False, True))
    for preset in args.presets:
        for name in args.policies:
            cls = POLICIES[name]
            updates, compile_s = {}, {}
            for label, pack, bf16, compile_ in configs:
                updates[label] = Update(cls, preset, pack, bf16, compile_, buffer, device, args.seed)
                start = time.perf_counter()
                updates[label].gradient(slice(0, min(args.batches)))  # warm-up (and compilation)
                compile_s[label] = time.perf_counter() - start
            reference = updates["padded"].gradient(slice(0, min(args.batches)))
            checks = {}
            for label, update in updates.items():
                grad = update.gradient(slice(0, min(args.batches)))
                checks[label] = (
                    float(((grad - reference).abs().max() / reference.abs().max()).item()),
                    float(F.cosine_similarity(grad, reference, dim=0).item()),
                )
            for batch in args.batches:
                times: dict[str, list[float]] = {label: [] for label in updates}
                labels = list(updates)
                for repeat in range(args.repeats + 1):
                    for label in labels if repeat % 2 == 0 else labels[::-1]:
                        start = time.perf_counter()
                        updates[label].epoch(batch)
                        if repeat:  # the first epoch of each is a warm-up
                            times[label].append(time.perf_counter() - start)
                base = statistics.median(times["padded"])
                for label in labels:
                    median = statistics.median(times[label])
                    results.append(
                        dict(
                            preset=preset,
                            policy=name,
                            option=label,
                            batch=batch,
                            samples_per_s=args.samples / median,
                            speedup=base / median,
                            max_rel_grad=checks[label][0],
                            cosine=checks[label][1],
                            first_call_s=compile_s[label],
                        )
                    )
                    print(
                        f"[update-speed] {preset} {name} {label} batch {batch}: {args.samples / median:,.0f} samples/s ({base / median:.2f}x)",
                        flush=True,
                    )


def render(results: list[dict], args: argparse.Namespace, device: th.device, seconds: float, interrupted: bool = False) -> str:
    head, rows = results[0], results[1:]
    lines = [
        "# Speed of the PPO update: token packing, bfloat16, minibatch size",
        "",
        f"`python benchmarks/update_speed.py {' '.join(args.argv)}`; machine: {platform.node()} ({platform.machine()}, {device}, "
        f"{th.get_num_threads()} torch thread(s)), torch {th.__version__}; {datetime.date.today()}; {seconds:.0f} s.",
        "",
        f"Buffer: {args.samples} reset observations of {head['robots']} ({head['real_tokens']:.1f} real tokens of "
        f"{contract.MAX_TOKENS} on average), proprioception jittered. One epoch = SB3's PPO loss, backward, gradient "
        "clipping and an Adam step per minibatch; each option interleaved with the padded float32 update in one process, "
        f"median of {args.repeats} epochs. Gradient checks on one minibatch of {min(args.batches)} against the padded "
        "float32 update's gradient (same parameters and samples).",
        "",
        *(["**Interrupted** (SIGINT): the rows measured before it; the others are missing.", ""] if interrupted else []),
        "| preset | policy | option | minibatch | update samples/s | speed-up against padded fp32 | max relative gradient difference | gradient cosine |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['preset']} | {row['policy']} | {row['option']} | {row['batch']} | {row['samples_per_s']:,.0f} | "
            f"**{row['speedup']:.2f}x** | {row['max_rel_grad']:.1e} | {row['cosine']:.6f} |"
        )
    compiled = [row for row in rows if "compile" in row["option"]]
    if compiled:
        lines += [
            "",
            "torch.compile's first call (compilation): "
            + ", ".join(f"{r['preset']} {r['policy']} {r['first_call_s']:.0f} s" for r in compiled[:: len(args.batches)]),
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", nargs="+", default=["small", "paper"])
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=list(POLICIES), help="which policies to time")
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024], help="minibatch sizes")
    parser.add_argument("--samples", type=int, default=2048, help="samples in the buffer (one epoch)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--compile", action="store_true", help="also time torch.compile of evaluate_actions")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None, help="markdown report (default: results/update_speed_<device>.md)")
    import sys

    args = parser.parse_args()
    args.argv = sys.argv[1:]
    th.set_num_threads(args.threads)
    device = th.device(args.device)
    start = time.time()
    results: list[dict] = []
    try:
        measure(args, device, results)
    except KeyboardInterrupt:  # a time limit (`timeout -s INT`): write what was measured, then stop as interrupted
        if len(results) > 1:
            write(results, args, device, start, interrupted=True)
        raise
    write(results, args, device, start)


def write(results: list[dict], args: argparse.Namespace, device: th.device, start: float, interrupted: bool = False) -> None:
    output = args.output or Path("results") / f"update_speed_{device.type}.md"
    output.write_text(render(results, args, device, time.time() - start, interrupted))
    print(f"[update-speed] -> {output}")


if __name__ == "__main__":
    main()
