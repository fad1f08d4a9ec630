"""Stage 1 — teachers: one MetaMorph policy per training task, trained with PPO.

Hyperparameters come from the rl-zoo file of the profile (entry ``Unimal-<task>-v0``), updated by
the profile's ``overrides`` and ``policy_kwargs``. Each teacher is saved with its
``VecNormalize`` statistics, which distillation needs to show it observations the way it saw them.
"""

from __future__ import annotations

from pathlib import Path

from stable_baselines3 import PPO

from sb3_divmorph.algos.device_ppo import DevicePPO
from divmorph.pipeline.config import ConfigError, Profile, load_zoo_entry, teacher_policy, zoo_entry_id  # noqa: F401 -- re-exported
from divmorph.pipeline.folders import load_teachers, teacher_folder  # noqa: F401 -- load_teachers re-exported
from divmorph.pipeline.envs import make_vec_env, normalizer_for, profile_env_kwargs, resolve_device, task_env_name
from divmorph.pipeline.files import is_done
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import TrainingRun
from divmorph.profile import unknown_tasks
from unimal_envs.contract import TASK_NAMES


def teacher_run(
    profile: Profile, out: Path, task: str, progress_bar: bool = True, policy: str | None = None, root: str = "teachers"
) -> TrainingRun:
    """The (resumable) PPO run of one task's teacher.

    :param policy: the teacher's policy (default: :func:`teacher_policy`).
    :param root: folder of the teachers inside the run (another policy's teachers live elsewhere).
    """
    cfg = profile.teachers
    env_name = task_env_name(task)
    entry = load_zoo_entry(cfg.hyperparams, zoo_entry_id(profile, task), cfg.overrides)
    entry.policy = policy or teacher_policy(profile, task)
    policy_kwargs = {**entry.policy_kwargs, **cfg.policy_kwargs}
    robots = profile_robots(profile, "train")
    seed = profile.seed + 1000 * (TASK_NAMES.index(task) + 1)
    device = resolve_device(profile.device)

    def make_env():
        return make_vec_env(
            env_name,
            entry.n_envs,
            seed,
            profile.max_episode_steps,
            cfg.env_backend,
            cfg.worlds_per_robot,
            device,
            cfg.terrain_variants,
            morphologies=robots,
            **profile_env_kwargs(profile),
        )

    # On the batched backend, rollouts stay on the device (DevicePPO; the same PPO otherwise). The
    # balanced robot sampler reads per-world infos, which only SB3's VecEnv path builds.
    algo = DevicePPO if cfg.env_backend == "batched" and not entry.callbacks else PPO

    def make_model():
        venv = normalizer_for(make_env(), entry.normalize, entry.ppo_kwargs.get("gamma", 0.99))
        return algo(entry.policy, venv, policy_kwargs=policy_kwargs, seed=seed, device=device, verbose=0, **entry.ppo_kwargs)

    from sb3_divmorph.algos.recipe import BalancedRobotSampler  # the only callback a zoo entry may name

    callbacks = [BalancedRobotSampler(**kwargs) for _, kwargs in entry.callbacks]
    return TrainingRun(
        teacher_folder(out, task, root),
        cfg.n_timesteps,
        cfg.checkpoint_every,
        make_model,
        make_env,
        algo=algo,
        callbacks=callbacks,
        device=device,
        progress_bar=progress_bar,
    )


def train_teachers(
    profile: Profile,
    out: Path,
    tasks: list[str] | None = None,
    progress_bar: bool = True,
    policy: str | None = None,
    root: str = "teachers",
    backend=None,
) -> list[Path]:
    """Train (or resume, or skip when done) the teachers of ``tasks`` (default: the profile's).

    :param policy: train teachers of this policy instead of the profile's (into ``root``).
    :param root: their folder inside the run.
    :param backend: a :mod:`~divmorph.pipeline.grid` backend for the run's own teachers (default: local).
    :raises GridError: some teachers failed (the others finished).
    """
    from divmorph.pipeline.grid import Job, run_grid

    tasks = list(tasks or profile.teachers.tasks)
    # every name is checked before the first one is announced and trained
    mistake = unknown_tasks(tasks)
    if mistake is not None:
        raise ConfigError(mistake)
    unknown = [task for task in tasks if task not in profile.teachers.tasks]
    if unknown:
        raise ConfigError(f"task(s) {unknown} have no teacher in profile {profile.name!r}: {profile.teachers.tasks}")
    if policy is None and root == "teachers":
        # the run's own teachers: independent jobs of a grid (in this process, or on Ray)
        jobs = [Job(f"{__name__}:teacher_run", (task,), teacher_folder(out, task), f"teacher {task}") for task in tasks]
        for job in jobs:
            if is_done(job.folder):
                print(f"[teachers] {job.args[0]}: skipped, already trained in {job.folder}")
            else:
                print(
                    f"[teachers] {job.args[0]}: {teacher_policy(profile, job.args[0])} PPO for {profile.teachers.n_timesteps} steps -> {job.folder}"
                )
        run_grid(profile, out, jobs, backend, progress_bar).raise_on_failure()
        return [job.folder for job in jobs]
    done = []
    for task in tasks:
        folder = teacher_folder(out, task, root)
        if is_done(folder):
            print(f"[teachers] {task}: skipped, already trained in {folder}")
        else:
            print(f"[teachers] {task}: {policy or teacher_policy(profile, task)} PPO for {profile.teachers.n_timesteps} steps -> {folder}")
            teacher_run(profile, out, task, progress_bar, policy, root).run()
        done.append(folder)
    return done
