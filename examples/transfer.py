"""Transfer a distilled DivMorph student to a novel task with fixed gates (``prepare_transfer``).

    python examples/transfer.py runs/demo/student --task Escape --steps 20000

1. the student's gates read the new task's instruction embedding and each robot's morphology,
   once: the tailors they select (``UnitSelection.from_gates``) are the ones that will learn;
2. ``prepare_transfer`` freezes the gates and gives every weight its own learning rate: selected
   tailors 1x, shared knowledge (learngenes, other actor weights) ``learngene_scale`` (0.1x),
   unselected tailors 0 (they stay bit for bit); the critic trains at the full rate;
3. PPO trains on the novel task with the zoo's settings; the learngene / selected-tailor update
   ratio actually applied is measured (``rates.measured_ratio()``, about 0.1).

The student folder is a pipeline ``student/`` (``make demo``) or ``examples/distill_dagger.py``'s.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import sb3_divmorph  # noqa: F401  (policy aliases)
import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from sb3_divmorph.finetune import UnitSelection, prepare_transfer
from sb3_divmorph.policies import DivMorphPolicy
from sb3_divmorph.zoo import zoo_hyperparams
from unimal_envs.contract import NOVEL_TASKS
from unimal_envs.morphology.loader import morphology_files


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("student", type=Path, help="folder with the student's model.zip and vecnormalize.pkl")
    parser.add_argument("--task", default="Escape", choices=NOVEL_TASKS)
    parser.add_argument(
        "--steps",
        type=int,
        default=4096,
        help="PPO steps (at least 2 rollouts of 2 x 256: the zoo's "
        "learning rate decays linearly to 0 over the run, so the last update moves nothing)",
    )
    parser.add_argument("--robots", type=int, default=4, help="first N robots of the train set")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    th.set_num_threads(1)  # small models: a second thread only contends with the simulation

    env_id = f"Unimal-{args.task}-v0"
    robots = morphology_files("train")[: args.robots]
    hp = zoo_hyperparams(env_id, overrides=dict(n_envs=2, n_steps=256, batch_size=256, n_epochs=2))
    venv = make_vec_env(env_id, n_envs=hp.n_envs, seed=args.seed, env_kwargs=dict(morphologies=robots))
    # the student's observation statistics as a start; the reward statistics start afresh for the task
    venv = VecNormalize.load(str(args.student / "vecnormalize.pkl"), venv)
    venv.training, venv.norm_reward, venv.gamma = True, True, hp.ppo_kwargs["gamma"]

    student = PPO.load(args.student / "model.zip", device="cpu")
    model = PPO(DivMorphPolicy, venv, policy_kwargs=student.policy_kwargs, seed=args.seed, **hp.ppo_kwargs)
    model.policy.load_state_dict(student.policy.state_dict())

    # 1. what the gates select: one reset observation per robot, normalised as the student saw it
    probe = gym.make(env_id, morphologies=robots)
    first = [probe.reset(seed=args.seed, options={"morphology": i})[0] for i in range(len(robots))]
    probe.close()
    obs = venv.normalize_obs({key: np.stack([o[key] for o in first]) for key in first[0]})
    with th.no_grad():
        gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    print(
        f"{args.task}: gates select {selection.morphology.sum()} of {selection.morphology.size} morphology tailors "
        f"and {selection.task.sum()} of {selection.task.size} task tailors"
    )

    # 2. fixed gates and per-unit learning rates; 3. PPO on the novel task
    rates = prepare_transfer(model.policy, selection, learngene_scale=0.1)
    model.learn(args.steps)
    print(
        f"transferred for {model.num_timesteps} steps; applied learngene / selected-tailor update ratio "
        f"{rates.measured_ratio():.3f} (configured 0.1)"
    )


if __name__ == "__main__":
    main()
