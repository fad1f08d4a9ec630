"""DAgger distillation: two PPO teachers -> one DivMorph student, with the pieces the pipeline uses.

    python examples/distill_dagger.py                          # about 1 min on 2 CPU cores
    python examples/distill_dagger.py --steps 200000 --out runs/example   # a budget where teachers learn

1. a MetaMorph teacher per task (FT and Incline), trained with PPO and the rl-zoo settings of
   ``zoo_configs/ppo.yml`` (``zoo_hyperparams``), saved with its observation statistics;
2. DAgger into one DivMorph student on ``Unimal-MultiTask-v1``: ``TeacherMixingVecEnv`` executes
   the teacher's action with probability beta (annealed 0.5 -> 0), ``DAggerCallback`` labels every
   visited state with its task's teacher and minimises KL(teacher || student), ``ImitationPPO``
   makes that the only loss;
3. the student is saved as ``<out>/student/{model.zip,vecnormalize.pkl}``, the pipeline's layout,
   so ``examples/load_run_model.py``, ``transfer.py`` and ``export_actor.py`` read it.

At the default budget nothing learns to walk: the example shows the steps, not a result.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import LinearSchedule
from stable_baselines3.common.vec_env import VecNormalize

import unimal_envs
from sb3_divmorph import DAggerCallback, DivMorphPolicy, ImitationPPO, Teacher, TeacherMixingVecEnv, zoo_hyperparams
from unimal_envs.contract import TASK_NAMES, observation_space

TASKS = ["FT", "Incline"]
ROBOTS = "train"
#: a small Transformer, so that the example runs in about a minute on a laptop
SMALL = dict(d_model=32, n_layers=1, ff_dim=64)


def train_teacher(task: str, steps: int, folder: Path, seed: int) -> Teacher:
    """PPO with the zoo's settings for ``task``; saves model + statistics into ``folder``."""
    hp = zoo_hyperparams(unimal_envs.env_id(task), overrides=dict(n_envs=2, n_steps=256, batch_size=256, n_epochs=2))
    venv = VecNormalize(
        make_vec_env(unimal_envs.env_id(task), n_envs=hp.n_envs, seed=seed, env_kwargs=dict(morphologies=ROBOTS)),
        gamma=hp.ppo_kwargs["gamma"],
        **hp.normalize,
    )
    model = PPO(hp.policy, venv, policy_kwargs={**hp.policy_kwargs, **SMALL}, seed=seed, **hp.ppo_kwargs)
    model.learn(steps)
    folder.mkdir(parents=True, exist_ok=True)
    model.save(folder / "model.zip")
    venv.save(str(folder / "vecnormalize.pkl"))
    print(f"teacher {task}: {model.num_timesteps} steps -> {folder}")
    return Teacher.load(folder / "model.zip", folder / "vecnormalize.pkl", name=task, observation_space=observation_space())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=4096, help="env steps per teacher and for the student")
    parser.add_argument("--out", type=Path, default=Path("runs/example"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be a positive number of env steps, got {args.steps}")
    th.set_num_threads(1)  # small models: a second thread only contends with the simulation

    teachers = {TASK_NAMES.index(task): train_teacher(task, args.steps, args.out / "teachers" / task, args.seed) for task in TASKS}

    venv = make_vec_env("Unimal-MultiTask-v1", n_envs=2, seed=args.seed, env_kwargs=dict(tasks=TASKS, morphologies=ROBOTS))
    venv = TeacherMixingVecEnv(venv, teachers, beta=0.5, seed=args.seed)
    venv = VecNormalize(venv, norm_obs_keys=["proprioceptive"], norm_reward=False)
    student = ImitationPPO(
        DivMorphPolicy,
        venv,
        n_steps=256,
        batch_size=256,
        seed=args.seed,
        policy_kwargs=dict(**SMALL, n_morph_tailors=8, n_task_tailors=8, top_k_morph=2, top_k_task=2),
    )
    dagger = DAggerCallback(
        teachers,
        TASK_NAMES,
        beta=LinearSchedule(0.5, 0.0, 1.0),
        learning_rate=1e-3,
        epochs=2,
        batch_size=256,
        buffer_size=20_000,
        seed=args.seed,
    )
    student.learn(args.steps, callback=dagger)

    folder = args.out / "student"
    folder.mkdir(parents=True, exist_ok=True)
    student.save(folder / "model.zip")
    venv.save(str(folder / "vecnormalize.pkl"))
    print(
        f"student: {student.num_timesteps} steps of DAgger, {dagger.dataset.size} labelled states, tailors in use "
        f"after the last round: {dagger.tailor_usage['morphology'][-1]} morphology, {dagger.tailor_usage['task'][-1]} task -> {folder}"
    )
    print("(TensorBoard: pass tensorboard_log= to ImitationPPO for distill/loss, distill/kl/<task>, gates/*)")


if __name__ == "__main__":
    main()
