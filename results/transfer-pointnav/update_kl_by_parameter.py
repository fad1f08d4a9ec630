"""Which parameters make one fine-tuning update of the DivMorph student large on a novel task (issue 42).

On PointNav, at the race's fine-tuning rate, the DivMorph student fine-tuned as a dense network moves
its policy five times as far per update (approx. KL) as the dense distilled student MetaMorph⚗ does
(``results/transfer-pointnav``, the fully fine-tuned control). The two students share everything but
the parameterisation of their Transformer and decoder layers: a dense ``W`` in MetaMorph⚗, in the
DivMorph student ``W = T diag(s g) Q^T`` (a free tall factor ``T``, free singular values ``s``, gates
``g``, and a square factor ``Q = Q0 cayley(A)`` kept orthogonal through its generator ``A``). Adam moves
every parameter by about the learning rate per step, whatever its gradient's size, so how far one
step moves the policy depends on how the function responds to each parameter.

Each probe loads a model from a recorded run with its observation statistics frozen (as the race
does), collects one rollout with the race's PPO settings (4 envs x 512 steps on the training robots,
the model told the instruction its arm is told), and makes one PPO update (4 epochs of minibatch
512, Adam eps 1e-10, the race's first learning rate) training only one group of the actor's
parameters; it reports SB3's ``train/approx_kl`` (mean over the update's minibatches) and the clip
fraction, over ``--seeds`` rollouts. The groups: the factors ``T``, ``s``, ``A`` of every factorized
layer alone, the rest of the actor, the router; MetaMorph⚗'s weights of the same layers alone; and
the DivMorph arm's own set-up (fixed gates, per-unit rates) at the race's learngene rate and at 1x,
and at 1x with the Cayley generators slower (``transfer.rotation_lr_scale``).

    python results/transfer-pointnav/update_kl_by_parameter.py --run results/cpu100 --task PointNav --gates-of Patrol \
        --out results/transfer-pointnav/update-kl-by-parameter.md      # ~15 min on one core
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.logger import configure

import sb3_divmorph  # noqa: F401
import unimal_envs  # noqa: F401
from sb3_divmorph.algos.finetune import critic_modules, prepare_transfer, set_adam_eps
from sb3_divmorph.nn.layers import FactorizedLinear
from divmorph.pipeline.envs import inherited_normalizer, make_vec_env, robot_observations
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import stage_model
from divmorph.pipeline.transfer import gate_selection
from unimal_envs.instructions import INSTRUCTIONS

ADAM_EPS = 1e-10  # the race's (transfer.adam_eps)
CRITIC_SCALE = 10.0  # the race's critic_lr_scale; the critic has its own network, so it moves no action


def factorized_layers(policy) -> dict[str, FactorizedLinear]:
    """The actor's factorized layers by module name."""
    return {name: module for name, module in policy.named_modules() if isinstance(module, FactorizedLinear)}


def probe(run: Path, folder: str, task: str, instruction: str, robots, lr: float, seed: int, trains, setup=None):
    """approx KL and clip fraction of one PPO update.

    :param trains: ``(name, parameter) -> bool``: the parameters that train (the others are frozen).
    :param setup: instead of ``trains``, the DivMorph arm's own set-up: ``(learngene rate scale, rotation rate scale)``.
    """
    env = make_vec_env(f"Unimal-{task}-v0", 4, 100 + seed, 1000, morphologies=robots, instruction=instruction)
    source = run / folder
    saved = PPO.load(stage_model(source), device="cpu")
    venv = inherited_normalizer(source, env, 0.99, freeze_observations=True)
    model = PPO(
        type(saved.policy), venv, policy_kwargs=saved.policy_kwargs, n_steps=512, batch_size=512, n_epochs=4,
        learning_rate=lr, seed=seed, device="cpu",
    )  # fmt: skip
    model.policy.load_state_dict(saved.policy.state_dict())
    set_adam_eps(model.policy.optimizer, ADAM_EPS)
    if setup is not None:
        raw = robot_observations(f"Unimal-{task}-v0", robots, 100, instruction=instruction)
        with th.no_grad():
            selection = gate_selection(model.policy, raw, venv)
        learngenes, rotations = setup
        prepare_transfer(model.policy, selection, learngenes, adam_eps=ADAM_EPS, critic_scale=CRITIC_SCALE, rotation_scale=rotations)
    else:
        critic = {id(p) for module in critic_modules(model.policy) for p in module.parameters()}
        for name, parameter in model.policy.named_parameters():
            parameter.requires_grad_(id(parameter) in critic or trains(name, parameter))
    model.set_logger(configure(None, []))
    model.learn(2048)
    values = model.logger.name_to_value
    venv.close()
    return values["train/approx_kl"], values["train/clip_fraction"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default="results/cpu100")
    parser.add_argument("--task", default="PointNav", help="the novel task")
    parser.add_argument("--gates-of", default="Patrol", help="the training task whose instruction the DivMorph student is told")
    parser.add_argument("--lr", type=float, default=1e-4, help="the race's first fine-tuning rate")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default="results/transfer-pointnav/update-kl-by-parameter.md")
    args = parser.parse_args()
    th.set_num_threads(1)
    start = time.time()
    run = Path(args.run)
    robots = profile_robots(recorded_profile(run / "run.json"), "train")
    own, gated = INSTRUCTIONS[args.task], INSTRUCTIONS[args.gates_of]
    layers = sorted(factorized_layers(PPO.load(stage_model(run / "student"), device="cpu").policy))
    in_layers = lambda name: name.rsplit(".", 1)[0] in layers  # noqa: E731
    student = ("DivMorph student", "student", gated)
    dense = ("MetaMorph⚗", "students/distilled", own)
    probes = [
        (*dense, "every actor parameter", lambda n, p: True, None),
        (*dense, "the weights of the layers the DivMorph student factorizes", lambda n, p: in_layers(n) and n.endswith(".weight"), None),
        (*dense, "the rest of the actor", lambda n, p: not in_layers(n), None),
        (*student, "every actor parameter, router included (divmorph-finetuned)", lambda n, p: True, None),
        (*student, "tall factors T", lambda n, p: in_layers(n) and n.endswith(".tall"), None),
        (*student, "singular values s", lambda n, p: in_layers(n) and n.endswith(".singular_values"), None),
        (*student, "Cayley generators A", lambda n, p: in_layers(n) and n.endswith(".square_skew"), None),
        (*student, "the rest of the actor, router excluded", lambda n, p: not in_layers(n) and "router" not in n, None),
        (*student, "the router", lambda n, p: "router" in n, None),
        (*student, "the DivMorph arm's set-up, learngenes at 0.1x (the race's rule)", None, (0.1, 1.0)),
        (*student, "the DivMorph arm's set-up, learngenes at 1x", None, (1.0, 1.0)),
        *(
            (*student, f"the DivMorph arm's set-up, learngenes at 1x, rotations at {rotations:g}x", None, (1.0, rotations))
            for rotations in (0.1, 0.03, 0.01, 0.0)
        ),
    ]
    lines = [
        f"# One fine-tuning update on {args.task}, by the parameters that train",
        "",
        f"`python results/transfer-pointnav/update_kl_by_parameter.py --run {args.run} --task {args.task} --gates-of {args.gates_of} "
        f"--lr {args.lr:g} --seeds {' '.join(map(str, args.seeds))}`; {platform.node()} ({platform.machine()}, 1 torch "
        f"thread). One rollout of 4 x 512 steps on the run's training robots (the DivMorph student told {args.gates_of}'s "
        f"instruction, as `transfer.task_gates: closest` tells it; MetaMorph⚗ {args.task}'s own), observation statistics "
        f"frozen, then one PPO update (4 epochs, minibatch 512, learning rate {args.lr:g}, Adam eps {ADAM_EPS:g}) training "
        "only the group named; SB3's approx KL and clip fraction, mean [min, max] over the rollout seeds.",
        "",
        "| model | what trains | approx. KL | clip fraction |",
        "|---|---|---|---|",
    ]
    for label, folder, instruction, group, trains, setup in probes:
        kls, clips = zip(*(probe(run, folder, args.task, instruction, robots, args.lr, s, trains, setup) for s in args.seeds))
        lines.append(
            f"| {label} | {group} | {np.mean(kls):.3f} [{min(kls):.3f}, {max(kls):.3f}] | "
            f"{np.mean(clips):.2f} [{min(clips):.2f}, {max(clips):.2f}] |"
        )
        print(lines[-1], flush=True)
    lines += ["", f"Wall time: {time.time() - start:.0f} s.", ""]
    Path(args.out).write_text("\n".join(lines))


if __name__ == "__main__":
    main()
