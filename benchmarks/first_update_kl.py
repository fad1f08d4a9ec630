"""Where a fine-tuned distilled student's huge first-update KL comes from (issue 26): one PPO update on a *training* task.

Each probe starts a model from a recorded run's trained weights with their observation statistics
frozen (as transfer now does), collects one rollout of 4 x 512 steps on the training robots and
makes one PPO update at the cpu profile's transfer settings (learning rate 1e-3 = the start of
lin_1e-3, 4 epochs of minibatch 512), training only the listed parameters, and reports SB3's
``train/approx_kl`` and clip fraction. Writes ``results/first_update_kl.md``.

    python benchmarks/first_update_kl.py            # ~2 min on one core
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.logger import configure

import sb3_divmorph  # noqa: F401
import unimal_envs  # noqa: F401
from sb3_divmorph.finetune import set_adam_eps
from sb3_divmorph.pipeline.grl import inherited_normalizer
from sb3_divmorph.pipeline.provenance import recorded_profile
from sb3_divmorph.pipeline.runs import make_vec_env, profile_robots

ACTOR = {
    "token embedding weight": "features_extractor.embedding.linear.weight",
    "token embedding bias": "features_extractor.embedding.linear.bias",
    "position embedding": "features_extractor.embedding.position",
    "Transformer": "features_extractor.encoder",
    "exteroception encoders": "features_extractor.exteroception",
    "decoder": "mlp_extractor.policy_net",
    "action head": "action_net",
}


def probe(run: Path, model_folder: str, task: str, robots, trains: list[str] | None, eps: float, lr: float = 1e-3) -> tuple[float, float]:
    """approx KL and clip fraction of one update; ``trains``: the actor parts that train (``None``: all)."""
    source = run / model_folder
    saved = PPO.load(source / "model.zip", device="cpu")
    venv = inherited_normalizer(source, make_vec_env(f"Unimal-{task}-v0", 4, 100, 1000, morphologies=robots), 0.99,
                                freeze_observations=True)
    model = PPO(type(saved.policy), venv, policy_kwargs=saved.policy_kwargs, n_steps=512, batch_size=512, n_epochs=4,
                learning_rate=lr, seed=0, device="cpu")
    model.policy.load_state_dict(saved.policy.state_dict())
    set_adam_eps(model.policy.optimizer, eps)
    if trains is not None:
        frozen = [ACTOR[part] for part in ACTOR if part not in trains] + ["router", "log_std"]
        for name, p in model.policy.named_parameters():
            if name.startswith(tuple(frozen)):
                p.requires_grad_(False)
    model.set_logger(configure(None, []))
    model.learn(2048)
    values = model.logger.name_to_value
    venv.close()
    return values["train/approx_kl"], values["train/clip_fraction"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default="results/cpu")
    parser.add_argument("--task", default="FT", help="a training task")
    parser.add_argument("--out", default="results/first_update_kl.md")
    args = parser.parse_args()
    th.set_num_threads(1)
    start = time.time()
    run = Path(args.run)
    robots = profile_robots(recorded_profile(run / "run.json"), "train")
    probes = [
        ("FT teacher", "teachers/FT", None, 1e-5, 1e-3),
        ("dense distilled student", "students/distilled", None, 1e-5, 1e-3),
        ("dense distilled student", "students/distilled", None, 1e-10, 1e-3),
        ("DivMorph student (all parameters)", "student", None, 1e-10, 1e-3),
        ("dense distilled student", "students/distilled", [], 1e-5, 1e-3),
        *(("dense distilled student", "students/distilled", [part], 1e-5, 1e-3) for part in ACTOR),
        ("DivMorph student (all parameters)", "student", ["token embedding weight"], 1e-10, 1e-3),
        ("dense distilled student", "students/distilled", None, 1e-5, 1e-4),
        ("dense distilled student", "students/distilled", None, 1e-5, 1e-5),
    ]
    lines = ["# First-update KL of fine-tuned models on a training task", "",
             f"`python benchmarks/first_update_kl.py --run {args.run} --task {args.task}`; machine: {platform.node()} "
             f"({platform.machine()}, 1 torch thread). One rollout of 4 x 512 steps on the run's training robots, observation "
             "statistics frozen, then one PPO update (4 epochs, minibatch 512); SB3's `train/approx_kl` (mean over the update's "
             "minibatches) and clip fraction. A log-probability check before the first step found rollout and update agree "
             "exactly (log ratio 0), so the KL is the update's.", "",
             "| model | Adam eps | learning rate | actor parts that train | approx KL | clip fraction |", "|---|---|---|---|---|---|"]
    for label, folder, trains, eps, lr in probes:
        kl, clip = probe(run, folder, args.task, robots, trains, eps, lr)
        parts = "all" if trains is None else (", ".join(trains) or "none (critic only)")
        lines.append(f"| {label} | {eps:.0e} | {lr:.0e} | {parts} | {kl:.3f} | {clip:.2f} |")
        print(lines[-1], flush=True)
    lines += ["", "What the rows say (recorded run `results/cpu`, FT): on a task both were trained for, one update at the "
              "transfer learning rate moves the distilled students' policies by a KL of hundreds where their FT teacher moves by "
              "0.36; Adam's eps does not matter; the critic alone moves nothing; of the actor's parts, the token embedding's "
              "weight alone (the linear map of the 52 proprioceptive + 35 context columns, times sqrt(d_model)) gives most of it, "
              "its bias and the position embedding nothing; a 10x smaller learning rate brings it to 0.05. Training the embedding "
              "weight's columns in three groups (dynamic proprioception, static proprioception, context) one group at a time gave "
              "0.06, 0.10 and 0.05 (a probe not in this table), so the effect needs the coherent step of all columns together: "
              "the distilled students respond to one Adam step on every input column of the embedding far more than their "
              "teacher does. Why (e.g. the scale of their residual stream relative to that step) is not resolved here.", ""]
    lines += ["", f"Wall time: {time.time() - start:.0f} s.", ""]
    Path(args.out).write_text("\n".join(lines))


if __name__ == "__main__":
    main()
