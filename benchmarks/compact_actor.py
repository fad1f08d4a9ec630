"""Deployment sizes, like for like: the pruned DivMorph actor vs MetaMorph's, through the same folding.

    python benchmarks/compact_actor.py                                               # -> results/compact_actor.md
    python benchmarks/compact_actor.py --profile cpu --out results/compact_actor_cpu.md  # a profile's student sizes

For each diversion configuration (``DivMorphPolicy(diversion=...)``) at the ``paper`` width (or at the
sizes of a pipeline profile's student, whose own diversion is then the ``default`` row) and each
task, a DivMorph student (random init: sizes and FLOPs do not depend on the weights' values) is
pruned and merged for one robot and task (:class:`sb3_divmorph.deploy.compact.CompactActor`), and the
MetaMorph actor of the same task and sizes is exported through the very same folding. Side by side,
in one run: stored weights of both and their ratio (the like-for-like reduction), what folding
alone saves MetaMorph, FLOPs per control step (``torch.utils.flop_counter``), batch-1 latency of
both exported actors (TorchScript, 1 thread) and the max |diff| of the compact actor to the student.
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
from sb3_divmorph.deploy.compact import CompactActor, actor_inputs, batch1_latency, export_torchscript, metamorph_twin, size_comparison  # noqa: E402
from sb3_divmorph.deploy.deployment import matmul_flops  # noqa: E402
from sb3_divmorph.policies import DivMorphPolicy  # noqa: E402
from unimal_envs.morphology.loader import morphology_files  # noqa: E402
from unimal_envs.tasks import TASKS  # noqa: E402

#: diversion configurations swept (names of ``sb3_divmorph.policies.DIVERSIONS``)
CONFIGS = ("default", "deploy-g4k2", "deploy-g2k1", "deploy-g1k1")
#: structural targets of the deployment issue (random-init students)
TARGETS = {"flat": 20.0, "height map": 12.0}


def policy_kwargs(config: str, profile_name: str | None) -> dict:
    """The student of ``config``: at the paper width, or as the pipeline distils it for a profile."""
    if profile_name is None:
        return dict(preset="paper", diversion=config)
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.distill import STUDENTS

    return STUDENTS["divmorph" if config == "default" else config].policy_kwargs(load_profile(profile_name))


def measure(config: str, task: str, repeats: int, folder: Path, kwargs: dict) -> dict:
    th.manual_seed(0)
    robot = morphology_files("train")[0]
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=[robot])]), norm_obs_keys=["proprioceptive"])
    venv.reset()
    raw = venv.get_original_obs()
    policy = DivMorphPolicy(venv.observation_space, venv.action_space, lambda _: 3e-4, **kwargs).eval()
    first = {k: v[0] for k, v in raw.items()}
    keys = TASKS[task].observation_keys
    actor = CompactActor.from_policy(policy, first, keys, venv)
    reference = CompactActor.from_policy(metamorph_twin(policy).eval(), first, keys, venv)
    sizes = size_comparison(policy, actor, first, keys, venv)
    inputs = actor_inputs(raw, batch=True)
    loaded = th.jit.load(str(export_torchscript(actor, first, folder / f"{task}-{config}.pt", {"config": config})))
    loaded_reference = th.jit.load(str(export_torchscript(reference, first, folder / f"{task}-metamorph.pt", {})))
    obs, _ = policy.obs_to_tensor(venv.normalize_obs(raw))
    with th.no_grad():
        diff = (policy.get_distribution(obs).distribution.mean - loaded(*inputs)).abs().max().item()
    return dict(
        config=config,
        task=task,
        kind="height map" if "hfield" in keys else "flat",
        **sizes,
        diff=diff,
        flops=matmul_flops(actor, inputs),
        flops_metamorph=matmul_flops(reference, inputs),
        compact_ms=batch1_latency(loaded, inputs, repeats) * 1e3,
        metamorph_ms=batch1_latency(loaded_reference, inputs, repeats) * 1e3,
        tokens=int(len(actor.real_tokens)),
        sizes={k: policy.config[k] for k in ("d_model", "n_layers", "ff_dim")},
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["FT", "VT", "Escape", "ManipulateBox"])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--profile", default=None, help="measure the students of this pipeline profile instead of the paper width")
    parser.add_argument("--out", default="results/compact_actor.md")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    folder = Path("runs/benchmarks")
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows = [
        measure(config, task, args.repeats, folder, policy_kwargs(config, args.profile)) for config in args.configs for task in args.tasks
    ]
    sizes = rows[0]["sizes"]
    width = (
        f"profile `{args.profile}`'s student sizes" if args.profile else "`paper` width"
    ) + f" (d_model {sizes['d_model']}, {sizes['n_layers']} layer(s), FFN {sizes['ff_dim']})"
    lines = [
        "# Deployment sizes, like for like: pruned DivMorph actor vs MetaMorph actor (same folding)",
        "",
        f"`python benchmarks/compact_actor.py{f' --profile {args.profile}' if args.profile else ''}` — {time.strftime('%Y-%m-%d')}, {platform.machine()} CPU "
        f"({os.cpu_count()} cores), torch {th.__version__}, {args.threads} thread(s), batch 1, median of {args.repeats} calls; "
        f"{width}, robot train-000 ({rows[0]['tokens']} real tokens); "
        f"{time.perf_counter() - start:.0f} s.",
        "Random-init students: sizes and FLOPs do not depend on the weights' values (whether a student of a "
        "configuration reaches the teachers' return is measured in the reduced-scale reproduction).",
        "",
        "| diversion | task | MetaMorph actor, folded | compact DivMorph | reduction (like for like) | target | "
        "MetaMorph unfolded (folding alone) | FLOPs/step MetaMorph / compact | latency MetaMorph / compact (ms) | max abs diff |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        target = TARGETS[r["kind"]]
        met = "met" if r["reduction"] >= target else "not met"
        lines.append(
            f"| {r['config']} | {r['task']} ({r['kind']}) | {r['metamorph_folded']:,} | {r['compact']:,} | **{r['reduction']:.1f}x** | "
            f">= {target:.0f}x: {met} | {r['metamorph_actor']:,} ({r['folding']:.2f}x) | "
            f"{r['flops_metamorph'] / 1e6:.2f}M / {r['flops'] / 1e6:.2f}M ({r['flops_metamorph'] / r['flops']:.1f}x) | "
            f"{r['metamorph_ms']:.3f} / {r['compact_ms']:.3f} ({r['metamorph_ms'] / r['compact_ms']:.1f}x) | {r['diff']:.1e} |"
        )
    lines += [
        "",
        "Both actors are exported by `CompactActor` from the same observation: context rows, the position embedding, padded",
        "tokens and the encoders of observations the task lacks become constants on both sides, so the reduction counts",
        "pruning only; 'folding alone' is what folding saves MetaMorph (the old table credited it to pruning).",
        "Weights count every stored number (folded constants included); baked normalisation statistics are not counted.",
        "Diversions (`sb3_divmorph.policies.DIVERSIONS`): `default` = the preset's 16 + 16 tailors per layer with top-8",
        "gates (with `--profile`: the profile's own student); `deploy-gNkK` = N learngenes per layer, the rest of each layer's rank split into morphology and task",
        "tailors, top-K per gate, exteroception encoders diverted too. The paper reports 16.7x (flat) and 8.9x (height map).",
    ]
    text = "\n".join(lines) + "\n"
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
