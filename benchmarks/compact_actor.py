"""Size and batch-1 CPU latency of the pruned compact actor, side by side with the full models.

    python benchmarks/compact_actor.py            # -> results/compact_actor.md

For each size preset and diversion configuration, a DivMorph student (random init: sizes and speed
do not depend on training) is pruned and merged for one robot and task
(:class:`sb3_divmorph.compact.CompactActor`). The script checks the compact actor against the
student (max |diff|), and reports in one run: stored weights of the compact actor, of the MetaMorph
actor of the same width/depth (the paper's reference, 16.7x), of the student's actor, and the
median batch-1 latency of the compact actor (TorchScript) vs the student's actor (eager PyTorch).
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
from sb3_divmorph.compact import CompactActor, actor_inputs, actor_parameter_count, batch1_latency, export_torchscript  # noqa: E402
from sb3_divmorph.pipeline.export import metamorph_twin  # noqa: E402
from sb3_divmorph.policies import DivMorphPolicy  # noqa: E402
from unimal_envs.morphology.loader import morphology_files  # noqa: E402
from unimal_envs.tasks import TASKS  # noqa: E402

CONFIGS = {
    # the package defaults: a quarter of each layer's units are tailors, half of them active
    "small, default diversion": dict(preset="small"),
    # most units are tailors and few are active: what deployment pruning is for
    "small, sparse diversion": dict(preset="small", n_morph_tailors=28, n_task_tailors=28, top_k_morph=4, top_k_task=4),
    "paper, default diversion": dict(preset="paper"),
    "paper, sparse diversion": dict(preset="paper", n_morph_tailors=60, n_task_tailors=60, top_k_morph=4, top_k_task=4),
}


def measure(name: str, kwargs: dict, task: str, repeats: int, folder: Path) -> dict:
    th.manual_seed(0)
    robot = morphology_files("train")[0]
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(f"Unimal-{task}-v0", morphologies=[robot])]), norm_obs_keys=["proprioceptive"])
    venv.reset()
    raw = venv.get_original_obs()
    policy = DivMorphPolicy(venv.observation_space, venv.action_space, lambda _: 3e-4, **kwargs).eval()
    first = {k: v[0] for k, v in raw.items()}
    actor = CompactActor.from_policy(policy, first, TASKS[task].observation_keys, venv)
    path = export_torchscript(actor, first, folder / f"{task}.pt", {"config": name})
    loaded = th.jit.load(str(path))
    obs, _ = policy.obs_to_tensor(venv.normalize_obs(raw))
    with th.no_grad():
        diff = (policy.get_distribution(obs).distribution.mean - loaded(*actor_inputs(raw, batch=True))).abs().max().item()
    compact_s = batch1_latency(loaded, actor_inputs(raw, batch=True), repeats)
    student_s = batch1_latency(lambda o: policy.get_distribution(o).distribution.mean, (obs,), repeats)
    weights = actor.stored_numbers()["weights"]
    metamorph = actor_parameter_count(metamorph_twin(policy))
    return dict(config=name, task=task, compact=weights, metamorph=metamorph, student=actor_parameter_count(policy),
                diff=diff, compact_ms=compact_s * 1e3, student_ms=student_s * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["FT", "VT"])
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="results/compact_actor.md")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    folder = Path("runs/benchmarks")
    folder.mkdir(parents=True, exist_ok=True)
    rows = [measure(name, kwargs, task, args.repeats, folder) for name, kwargs in CONFIGS.items() for task in args.tasks]
    lines = [
        "# Compact (pruned + merged) actor vs full models",
        "",
        f"`python benchmarks/compact_actor.py` — {time.strftime('%Y-%m-%d')}, {platform.machine()} CPU, "
        f"torch {th.__version__}, {args.threads} thread(s), batch 1, median of {args.repeats} calls; robot train-000.",
        "Random-init students (size and speed do not depend on the weights' values).",
        "",
        "| student config | task | compact weights | MetaMorph actor | reduction vs MetaMorph | student actor | max abs diff | latency compact / student (ms) | speed-up |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['config']} | {r['task']} | {r['compact']:,} | {r['metamorph']:,} | {r['metamorph'] / r['compact']:.1f}x | "
            f"{r['student']:,} | {r['diff']:.1e} | {r['compact_ms']:.3f} / {r['student_ms']:.3f} | {r['student_ms'] / r['compact_ms']:.1f}x |"
        )
    lines += [
        "",
        "Compact weights count every stored number of the actor, the folded constants included (context rows, position",
        "embedding, encoders of observations the task lacks: FT has no height map, VT keeps its 1410-input encoder).",
        "The paper reports 16.7x against MetaMorph; how far pruning goes depends on how many units stay active",
        "(learngenes + top-k tailors) per layer, which the diversion configuration sets.",
    ]
    text = "\n".join(lines) + "\n"
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
