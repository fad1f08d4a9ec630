"""Stage 3 — transfer to a novel task: the student with fixed gates vs MetaMorph from scratch.

The student's weights and observation statistics are loaded into a PPO run on the novel task
(``Unimal-<task>-v0`` on the training robots); its gates see the embedding of the task's
instruction (the built-in one, or ``transfer.instructions[task]`` of the profile, embedded by the
text encoder) and stay fixed; PPO trains the tailors those gates select and, ``learngene_lr_scale`` times slower, the
shared knowledge (:func:`sb3_divmorph.finetune.prepare_transfer`). With ``compare_scratch`` the same
budget trains a MetaMorph policy from scratch with the task's rl-zoo settings, so both learning
curves come from one command.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.finetune import UnitLearningRates, UnitSelection, prepare_transfer
from sb3_divmorph.pipeline.config import ConfigError, Profile, load_zoo_entry
from sb3_divmorph.pipeline.distill import student_folder
from sb3_divmorph.pipeline.runs import (
    MODEL,
    NORMALIZER,
    TrainingRun,
    is_done,
    make_vec_env,
    normalizer_for,
    profile_robots,
    resolve_device,
    task_env_name,
)
from sb3_divmorph.policies import DivMorphPolicy
from unimal_envs.contract import NOVEL_TASKS, TASK_NAMES

ARMS = ("divmorph", "scratch")


def transfer_folder(out: Path, task: str, arm: str) -> Path:
    return Path(out) / "transfer" / task / arm


def robot_observations(env_name: str, robots: list[Path], seed: int = 0, instruction: str | None = None) -> dict[str, np.ndarray]:
    """One reset observation per robot, batched (for gates and selections)."""
    import gymnasium as gym

    env = gym.make(env_name, morphologies=robots, **({"instruction": instruction} if instruction else {}))
    try:
        observations = [env.reset(seed=seed, options={"morphology": i})[0] for i in range(len(robots))]
    finally:
        env.close()
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


def gate_selection(policy: DivMorphPolicy, raw_obs: dict[str, np.ndarray], normalizer: VecNormalize | None) -> UnitSelection:
    """The tailors the student's gates select for these robots doing this task."""
    obs = raw_obs if normalizer is None else normalizer.normalize_obs(raw_obs)
    gates = policy.get_gates(obs)
    return UnitSelection.from_gates(gates.morphology.cpu().numpy(), gates.task.cpu().numpy())


class UpdateRatioLogger(BaseCallback):
    """Logs ``transfer/update_ratio``: the learngene / selected-tailor mean absolute update of the
    last rollout's optimiser steps, as applied (the configured ``learngene_lr_scale`` is the target).

    :param rates: returns the installed :class:`~sb3_divmorph.finetune.UnitLearningRates`.
    """

    def __init__(self, rates: Callable[[], UnitLearningRates | None]):
        super().__init__()
        self.rates = rates

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # the optimiser steps between two rollouts are the previous rollout's update
        rates = self.rates()
        if rates is not None and self.model.num_timesteps > 0:
            means = rates.mean_updates(reset=True)
            if means["selected_tailor"] > 0:
                self.logger.record("transfer/update_ratio", means["learngene"] / means["selected_tailor"])
                self.logger.record("transfer/update_selected_tailor", means["selected_tailor"])


def transfer_run(profile: Profile, out: Path, task: str, arm: str, progress_bar: bool = True) -> TrainingRun:
    if task not in NOVEL_TASKS:
        raise ConfigError(f"transfer targets a novel task; {task!r} is not one of {list(NOVEL_TASKS)}")
    if arm not in ARMS:
        raise ConfigError(f"unknown transfer arm {arm!r}; choose from {ARMS}")
    cfg = profile.transfer
    env_name = task_env_name(task)
    entry = load_zoo_entry(profile.teachers.hyperparams, env_name, cfg.overrides)
    robots = profile_robots(profile, "train")
    device = resolve_device(profile.device)
    seed = profile.seed + 7000 + TASK_NAMES.index(task)
    gamma = entry.ppo_kwargs.get("gamma", 0.99)
    env_kwargs = {"morphologies": robots}
    if task in cfg.instructions:
        env_kwargs["instruction"] = cfg.instructions[task]

    def make_env():
        return make_vec_env(env_name, entry.n_envs, seed, profile.max_episode_steps, **env_kwargs)

    prepare = None
    callbacks: list[BaseCallback] = []
    if arm == "scratch":
        policy_kwargs = {**entry.policy_kwargs, **profile.teachers.policy_kwargs}

        def make_model():
            venv = normalizer_for(make_env(), entry.normalize, gamma)
            return PPO("MetaMorphPolicy", venv, policy_kwargs=policy_kwargs, seed=seed, device=device, **entry.ppo_kwargs)

    else:
        source = student_folder(out)
        if not is_done(source):
            raise FileNotFoundError(f"no distilled student in {source}; run `divmorph distill --out {out}` first")
        selection_obs = robot_observations(env_name, robots, seed, env_kwargs.get("instruction"))

        def make_model():
            student = PPO.load(source / MODEL, device=device)
            venv = make_env()
            if (source / NORMALIZER).is_file():
                # the student's statistics as a start; the reward statistics start afresh for the new task
                venv = VecNormalize.load(str(source / NORMALIZER), venv)
                venv.training, venv.norm_reward = True, True
                venv.gamma = gamma
            model = PPO(DivMorphPolicy, venv, policy_kwargs=student.policy_kwargs, seed=seed, device=device, **entry.ppo_kwargs)
            model.policy.load_state_dict(student.policy.state_dict())
            return model

        installed: dict[str, UnitLearningRates] = {}

        def prepare(model):
            with th.no_grad():
                selection = gate_selection(model.policy, selection_obs, model.get_vec_normalize_env())
            # the hooks live on the optimiser; they are installed again whenever the run is loaded
            installed["rates"] = prepare_transfer(model.policy, selection, cfg.learngene_lr_scale)

        callbacks.append(UpdateRatioLogger(lambda: installed.get("rates")))

    return TrainingRun(
        transfer_folder(out, task, arm), cfg.n_timesteps, cfg.checkpoint_every, make_model, make_env,
        prepare=prepare, callbacks=callbacks, device=device, progress_bar=progress_bar,
    )


def transfer(profile: Profile, out: Path, tasks: list[str] | None = None, compare_scratch: bool | None = None, progress_bar: bool = True):
    """Transfer the student to ``tasks`` (default: the profile's) and, if asked, train MetaMorph from scratch."""
    compare = profile.transfer.compare_scratch if compare_scratch is None else compare_scratch
    tasks = tasks or profile.transfer.tasks
    # every name is checked before the first one is announced and trained
    unknown = [task for task in tasks if task not in NOVEL_TASKS]
    if unknown:
        raise ConfigError(f"transfer targets a novel task; {unknown} not one of {list(NOVEL_TASKS)}")
    for task in tasks:
        for arm in ARMS if compare else ARMS[:1]:
            folder = transfer_folder(out, task, arm)
            if is_done(folder):
                print(f"[transfer] {task} ({arm}): skipped, already trained in {folder}")
            else:
                print(f"[transfer] {task} ({arm}): PPO for {profile.transfer.n_timesteps} steps -> {folder}")
                transfer_run(profile, out, task, arm, progress_bar).run()
