"""What bfloat16 autocast (``policy_kwargs=dict(mixed_precision=True)``) changes in a policy: actions, log-probabilities, gradients, time.

For trained models of a recorded run (the FT teacher, the DivMorph student) and randomly initialised
paper-size MetaMorph and DivMorph policies, on states the trained model visits on a training task
(observation statistics of that model, frozen), the same parameters are run twice, float32 and
bfloat16 autocast, and compared:

* the action means: largest and root-mean-square difference, in units of the policy's action std;
* the log-probability of the float32 policy's sampled actions: the mean and largest absolute
  difference, i.e. how far the PPO ratio of a sample starts from 1 when rollout and update were
  computed in different precisions (inside one run both use the same precision, so a learning
  rate of 0 still gives ratio 1 exactly);
* the gradient of a PPO loss (clipped surrogate with the rollout's own advantages, value loss,
  SB3's coefficients) on one minibatch: cosine similarity and relative norm of bf16 vs float32;
* seconds per forward+backward of that minibatch in each precision (best of 3), on this machine (on a CPU
  bfloat16 is usually *slower*: the speed is a GPU question; run with ``--device cuda`` there).

    python benchmarks/mixed_precision.py                       # ~3 min on one core (restore results/cpu/teachers/FT first:
                                                               # its model is in git history, results/cpu/README.md)
    python benchmarks/mixed_precision.py --device cuda --out results/mixed_precision_gpu.md
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3 import PPO

import sb3_divmorph  # noqa: F401  (policy aliases)
import unimal_envs
from divmorph.pipeline.grl import inherited_normalizer
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.envs import make_vec_env
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import stage_model


def visited_states(run: Path, folder: str, task: str, robots, steps: int, device: str):
    """``steps`` x 4 normalised observations the trained model at ``run/folder`` visits (deterministic actions)."""
    source = run / folder
    model = PPO.load(stage_model(source), device=device)
    venv = inherited_normalizer(
        source, make_vec_env(unimal_envs.env_id(task), 4, 0, 1000, morphologies=robots), 0.99, freeze_observations=True
    )
    obs, batch = venv.reset(), []
    for _ in range(steps):
        action, _ = model.predict(obs, deterministic=True)
        obs, *_ = venv.step(action)
        batch.append({key: value.copy() for key, value in obs.items()})
    venv.close()
    return {key: th.as_tensor(np.concatenate([b[key] for b in batch]), device=device) for key in batch[0]}


def compare(policy, states: dict[str, th.Tensor], seed: int = 0) -> dict[str, float]:
    """float32 vs bfloat16-autocast passes of the same parameters on ``states`` (see the module docstring)."""
    policy.set_training_mode(False)
    th.manual_seed(seed)
    outputs = {}
    for precision in ("fp32", "bf16"):
        policy.mixed_precision = precision == "bf16"
        with th.no_grad():
            distribution = policy.get_distribution(states)
            if precision == "fp32":
                actions = distribution.get_actions()
            outputs[precision] = (distribution.distribution.mean, distribution.log_prob(actions), policy.predict_values(states))
    real = ~states["act_padding_mask"].bool()
    std = policy.log_std.exp().mean().item()
    mean_gap = (outputs["bf16"][0] - outputs["fp32"][0])[real] / std
    logp_gap = (outputs["bf16"][1] - outputs["fp32"][1]).abs()
    advantages = th.randn(len(actions), generator=th.Generator().manual_seed(seed)).to(actions.device)
    returns = outputs["fp32"][2].flatten() + advantages
    grads, seconds = {}, {}
    for precision in ("fp32", "bf16"):
        policy.mixed_precision = precision == "bf16"
        times = []
        for _ in range(3):  # the first pass of each precision pays one-off costs (allocations, kernel choice): best of 3
            policy.zero_grad(set_to_none=True)
            _synchronize(actions.device)
            start = time.perf_counter()
            values, log_prob, entropy = policy.evaluate_actions(states, actions)
            ratio = th.exp(log_prob - outputs["fp32"][1])
            surrogate = -th.min(advantages * ratio, advantages * th.clamp(ratio, 0.8, 1.2)).mean()
            loss = surrogate + 0.5 * (returns - values.flatten()).pow(2).mean()
            loss.backward()
            _synchronize(actions.device)
            times.append(time.perf_counter() - start)
        seconds[precision] = min(times)
        grads[precision] = th.cat([p.grad.flatten() for p in policy.parameters() if p.grad is not None])
    policy.mixed_precision = False
    cosine = th.nn.functional.cosine_similarity(grads["bf16"], grads["fp32"], dim=0).item()
    return {
        "mean_max": mean_gap.abs().max().item(),
        "mean_rms": mean_gap.pow(2).mean().sqrt().item(),
        "logp_mean": logp_gap.mean().item(),
        "logp_max": logp_gap.max().item(),
        "value_rms": (outputs["bf16"][2] - outputs["fp32"][2]).pow(2).mean().sqrt().item(),
        "cosine": cosine,
        "norm_ratio": (grads["bf16"].norm() / grads["fp32"].norm()).item(),
        "fp32_s": seconds["fp32"],
        "bf16_s": seconds["bf16"],
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default="results/cpu", help="recorded run whose models and training robots are used")
    parser.add_argument("--task", default="FT", help="a training task")
    parser.add_argument("--steps", type=int, default=64, help="control steps of the 4 envs whose states are compared")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("results/mixed_precision.md"))
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    start = time.time()
    run = Path(args.run)
    robots = profile_robots(recorded_profile(run / "run.json"), "train")
    states = visited_states(run, "teachers/FT", args.task, robots, args.steps, args.device)
    env = make_vec_env(unimal_envs.env_id(args.task), 1, 0, 1000, morphologies=robots)
    models = [
        ("FT teacher (trained)", PPO.load(stage_model(run / "teachers" / "FT"), device=args.device).policy),
        ("DivMorph student (trained)", PPO.load(stage_model(run / "student"), device=args.device).policy),
    ]
    for name, policy_class in (("MetaMorph", "MetaMorphPolicy"), ("DivMorph", "DivMorphPolicy")):
        th.manual_seed(0)
        fresh = PPO(policy_class, env, policy_kwargs=dict(preset="paper"), device=args.device)
        models.append((f"{name}, paper size (random init)", fresh.policy))
    rows = []
    for label, policy in models:
        result = compare(policy, states)
        rows.append((label, sum(p.numel() for p in policy.parameters()), result))
        print(label, {key: round(value, 5) for key, value in result.items()}, flush=True)
    lines = [
        "# bfloat16 autocast in the Transformer policies (`mixed_precision=True`)",
        "",
        f"`python benchmarks/mixed_precision.py --run {args.run} --task {args.task} --steps {args.steps} --device {args.device}`; "
        f"machine: {platform.node()} ({platform.machine()}, {args.device}, 1 torch thread), torch {th.__version__}; "
        f"{time.strftime('%Y-%m-%d')}; {time.time() - start:.0f} s.",
        "",
        f"States: {len(states['proprioceptive'])} observations the run's FT teacher visits on its training robots "
        "(its observation statistics, frozen). Each model runs the same parameters in float32 and under bfloat16 "
        "autocast (embedding, exteroception encoders, Transformer; decoders, heads and log-probabilities float32). "
        "Action-mean gaps are in units of the action std; log-probability gaps are of the float32 policy's sampled "
        "actions (a PPO ratio starts at exp(gap) when rollout and update use different precisions; within one run "
        "they use the same). Gradient: PPO's clipped surrogate (random advantages) + value loss on all states as one minibatch.",
        "",
        "| model | parameters | action mean gap: max / RMS (std) | log-prob gap: mean / max | value gap (RMS) "
        "| gradient cosine | gradient norm bf16/fp32 | fwd+bwd s: fp32 / bf16 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, count, r in rows:
        lines.append(
            f"| {label} | {count:,} | {r['mean_max']:.4f} / {r['mean_rms']:.4f} | {r['logp_mean']:.4f} / {r['logp_max']:.4f} "
            f"| {r['value_rms']:.4f} | {r['cosine']:.4f} | {r['norm_ratio']:.3f} | {r['fp32_s']:.3f} / {r['bf16_s']:.3f} |"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


def _synchronize(device: th.device) -> None:
    if device.type == "cuda":
        th.cuda.synchronize(device)


if __name__ == "__main__":
    main()
