"""Deployment comparison: the per-robot actors of MetaMorph, ModuMorph, HyperDistill and DivMorph, side by side.

    python benchmarks/deployment.py            # -> results/deployment.md

At the ``paper`` width, for one robot on FT and VT, every model is folded for that robot and task by
the same rules (everything constant for the robot and task becomes stored constants; padded tokens,
context encoders, hypernetworks, routers, critics and the encoders of observations the task lacks
are gone; observation normalisation baked in):

* MetaMorph: :class:`~sb3_divmorph.deploy.compact.CompactActor` ``.from_policy`` of a ``MetaMorphPolicy``
  (nothing to prune, only folded);
* ModuMorph: :class:`~sb3_divmorph.deploy.modumorph_actor.ModuMorphActor` (generated weights and the fixed
  attention matrices stored per limb);
* HyperDistill: :class:`~sb3_divmorph.deploy.hyperdistill_mlp.HyperDistillMLP` (the generated MLP);
* DivMorph: :class:`~sb3_divmorph.deploy.compact.CompactActor` ``.from_policy`` of a ``DivMorphPolicy``
  with the ``deploy-g1k1`` diversion (1 learngene per layer, top-1 morphology and task tailors,
  exteroception encoders diverted; see ``compact_actor.md`` for every diversion).

Random-init models: sizes and costs do not depend on the weights' values. Each actor is checked
against its policy (max |diff|), then measured: stored numbers, FLOPs of one control step
(``torch.utils.flop_counter``: 2 per multiply-add of matmuls / linear layers / attention), and the
median batch-1 latency of its TorchScript file on one CPU thread.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402

import sb3_divmorph  # noqa: E402,F401
import unimal_envs  # noqa: E402,F401
from sb3_divmorph import DivMorphPolicy, HyperDistillPolicy, MetaMorphPolicy, ModuMorphPolicy  # noqa: E402
from sb3_divmorph.deploy.compact import CompactActor, actor_inputs, batch1_latency, export_torchscript  # noqa: E402
from sb3_divmorph.deploy.deployment import matmul_flops  # noqa: E402
from sb3_divmorph.deploy.hyperdistill_mlp import HyperDistillMLP  # noqa: E402
from sb3_divmorph.deploy.modumorph_actor import ModuMorphActor  # noqa: E402
from unimal_envs.morphology.loader import morphology_files  # noqa: E402
from unimal_envs.tasks import TASKS  # noqa: E402

DIVMORPH_DIVERSION = "deploy-g1k1"


def decoder(task: str) -> dict:
    # MetaMorph's decoders: Linear(128 + extero -> 2) on flat tasks, one hidden [64] on VT
    return dict(net_arch=dict(pi=[], vf=[])) if not TASKS[task].observation_keys else {}


def build(name: str, task: str, space, action_space):
    th.manual_seed(0)
    kwargs = dict(preset="paper", **decoder(task))
    if task == "FT":
        kwargs["exteroception"] = {}
    if name == "MetaMorph":
        return MetaMorphPolicy(space, action_space, lambda _: 0.0, **kwargs)
    if name == "ModuMorph":
        policy = ModuMorphPolicy(space, action_space, lambda _: 0.0, **kwargs)
        with th.no_grad():  # generators start at zero; move them so every limb's weights differ
            for n, p in policy.named_parameters():
                if "generator.weight" in n:
                    p.normal_(0, 1e-3)
        return policy
    if name == "HyperDistill":
        policy = HyperDistillPolicy(space, action_space, lambda _: 0.0, preset="paper", **({"exteroception": {}} if task == "FT" else {}))
        with th.no_grad():
            for n, p in policy.named_parameters():
                if n.endswith(("weight.weight", "bias.weight")) and "network." in n and "encoders" not in n:
                    p.normal_(0, 1e-3)
        return policy
    return DivMorphPolicy(space, action_space, lambda _: 0.0, diversion=DIVMORPH_DIVERSION, **kwargs)


def fold(name: str, policy, observation, keys, normalizer):
    if name == "ModuMorph":
        return ModuMorphActor.from_policy(policy, observation, keys, normalizer)
    if name == "HyperDistill":
        return HyperDistillMLP.from_policy(policy, observation, keys, normalizer)
    return CompactActor.from_policy(policy, observation, keys, normalizer)


def measure(task: str, repeats: int, folder: Path) -> list[dict]:
    robot = morphology_files("train")[0]
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=[robot])]), norm_obs_keys=["proprioceptive"])
    venv.reset()
    for _ in range(20):  # statistics that are not the identity
        venv.step(th.empty(1, 24).uniform_(-1, 1).numpy())
    venv.training = False
    raw = venv.get_original_obs()
    first = {k: v[0] for k, v in raw.items()}
    rows = []
    for name in ("MetaMorph", "ModuMorph", "HyperDistill", "DivMorph"):
        policy = build(name, task, venv.observation_space, venv.action_space).eval()
        actor = fold(name, policy, first, TASKS[task].observation_keys, venv)
        path = export_torchscript(actor, first, folder / f"{name}-{task}.pt", {"model": name, "task": task})
        loaded = th.jit.load(str(path))
        inputs = actor_inputs(raw, batch=True)
        with th.no_grad():
            reference = policy.get_distribution(policy.obs_to_tensor(venv.normalize_obs(raw))[0]).distribution.mean
            diff = (reference - loaded(*inputs)).abs().max().item()
        rows.append(
            dict(
                model=name,
                task=task,
                weights=actor.stored_numbers()["weights"],
                flops=matmul_flops(actor, inputs),
                latency_ms=batch1_latency(loaded, inputs, repeats) * 1e3,
                diff=diff,
                real_tokens=int(len(actor.real_tokens)),
            )
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["FT", "VT"])
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="results/deployment.md")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    folder = Path("runs/benchmarks")
    folder.mkdir(parents=True, exist_ok=True)
    rows = [row for task in args.tasks for row in measure(task, args.repeats, folder)]
    lines = [
        "# Deployment: per-robot actors of MetaMorph, ModuMorph, HyperDistill and DivMorph",
        "",
        f"`python benchmarks/deployment.py` — {time.strftime('%Y-%m-%d')}, {platform.machine()} CPU ({platform.node()}), "
        f"torch {th.__version__}, {args.threads} thread(s), batch 1, median of {args.repeats} calls of the TorchScript file; "
        f"robot train-000 ({rows[0]['real_tokens']} real tokens). `paper` width (128, 5 layers, FFN 1024; HyperDistill 2 x 256).",
        "Every actor folded for the robot and task by the same rules (see the script's docstring); random-init models.",
        "FLOPs: `torch.utils.flop_counter` on one control step (2 per multiply-add; element-wise ops, norms, softmax not counted).",
        "",
        "| task | actor | stored weights | x fewer than MetaMorph | FLOPs / step | x fewer than MetaMorph | latency (ms) | max abs diff vs policy |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        base = next(b for b in rows if b["task"] == r["task"] and b["model"] == "MetaMorph")
        lines.append(
            f"| {r['task']} | {r['model']} | {r['weights']:,} | {base['weights'] / r['weights']:.1f}x | {r['flops']:,} | "
            f"{base['flops'] / r['flops']:.1f}x | {r['latency_ms']:.3f} | {r['diff']:.1e} |"
        )
    lines += [
        "",
        "HyperDistill reports 6-14x fewer parameters and 67-160x fewer FLOPs than the Transformer. The ratios above are",
        "against a MetaMorph actor folded the same way (its context rows, position embedding and padded tokens folded, the",
        "actor running on the robot's real tokens only), so folding is not credited to any model.",
    ]
    text = "\n".join(lines) + "\n"
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
