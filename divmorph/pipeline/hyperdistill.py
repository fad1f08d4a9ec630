"""HyperDistill baseline stage: distil the teachers into a hypernetwork student, export per-robot MLPs.

Runs when the profile has a ``hyperdistill`` section (``divmorph hyperdistill`` runs it alone):

1. teachers of ``hyperdistill.teacher_policy`` (ModuMorph by default): the run's own teachers when
   they are of that policy, else trained with the ``teachers`` settings into ``hyperdistill/teachers/``;
2. the student (``hyperdistill/student/``): offline from ``rollout_samples`` teacher-rollout states on
   ``Unimal-MultiTask-v1`` over the training robots (loss ``nll`` or ``kl``), then optionally
   ``dagger_timesteps`` of DAgger on the states the student visits; ``model.zip`` + ``vecnormalize.pkl``.
   One student for all the training tasks: the one-hot of the task conditions its hypernetwork
   (the paper's one hypernetwork per task, in one network), and each state is normalised with the
   statistics of its task's teacher, held in ``model.zip`` (see :mod:`sb3_divmorph.policies.hyperdistill`).
   A student without a task input and with one ``VecNormalize`` of its own (``vecnormalize.pkl``)
   is exported too, for any task;
3. per (robot, task) of the ``export`` section: the MLP generated once for that robot, written as
   TorchScript (``mlp.pt``) and ONNX (``mlp.onnx``), checked against the student (max |diff| <= 1e-5)
   and reported with its size against the teacher's actor (``hyperdistill/export/<robot>-<task>/``).

Resumable: the teacher-rollout states are written to ``student/rollouts.npz`` once collected and the
offline fit checkpoints after every
epoch (``student/offline-fit.pt``), so a killed stage resumes from its last epoch; both are removed
once the student is saved. The DAgger phase, when there is one, starts over.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

from sb3_divmorph.algos.distillation import DAggerCallback, ImitationPPO, Teacher, load_normalizer
from sb3_divmorph.algos.hyperdistill_fit import TeacherRollouts, collect_teacher_rollouts, fit_offline, load_student
from sb3_divmorph.deploy.compact import actor_inputs, actor_parameter_count, batch1_latency, export_torchscript
from sb3_divmorph.deploy.deployment import export_onnx
from sb3_divmorph.deploy.hyperdistill_mlp import HyperDistillMLP
from divmorph.pipeline.config import ConfigError, Profile, teacher_policy
from divmorph.pipeline.folders import TEACHER_RUN, load_teachers, teacher_folder
from divmorph.pipeline.grid import Job, run_grid
from divmorph.pipeline.envs import make_vec_env, profile_env_kwargs, resolve_device, task_env_name
from divmorph.pipeline.files import MODEL, atomic_save, atomic_write_json, is_done, mark_done, read_done
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import stage_model, stage_normalizer
from sb3_divmorph.policies.hyperdistill import HyperDistillPolicy
from unimal_envs import MULTITASK_ID
from unimal_envs.contract import TASK_NAMES, observation_space
from unimal_envs.tasks import TASKS

NORM_OBS_KEYS = ["proprioceptive"]
#: The student folder's resume files, removed once the student is saved.
ROLLOUTS, FIT_CHECKPOINT = "rollouts.npz", "offline-fit.pt"
#: Largest accepted difference between an exported MLP and the student.
TOLERANCE = 1e-5


def hyperdistill_folder(out: Path) -> Path:
    return Path(out) / "hyperdistill"


def _config(profile: Profile):
    if profile.hyperdistill is None:
        raise ConfigError(f"profile {profile.name!r} has no 'hyperdistill' section")
    return profile.hyperdistill


def _any_task(student: Path) -> bool:
    """Whether the trained student in folder ``student`` can be written for a task without a teacher:
    one without a task input and with its own statistics."""
    info = read_done(student)
    return info.get("task_input") == "none" and info.get("observation_statistics") == "own"


def hyperdistill_teachers(profile: Profile, out: Path, progress_bar: bool = True) -> dict[int, Teacher]:
    """The teachers to distil: the run's own if they are ``teacher_policy``, else trained for it."""
    wanted = _config(profile).teacher_policy
    own = all(teacher_policy(profile, task) == wanted for task in profile.teachers.tasks)
    root, options = ("teachers", {}) if own else ("hyperdistill/teachers", {"policy": wanted, "root": "hyperdistill/teachers"})
    jobs = [
        Job(TEACHER_RUN, (task,), teacher_folder(out, task, root), f"{wanted} teacher {task}", options) for task in profile.teachers.tasks
    ]
    for job in jobs:
        if not (job.folder / "done.json").is_file():
            print(f"[hyperdistill] {job.label}: PPO for {profile.teachers.n_timesteps} steps -> {job.folder}")
    run_grid(profile, out, jobs, progress_bar=progress_bar).raise_on_failure()
    return load_teachers(profile, out, root=root)


def train_student(profile: Profile, out: Path, progress_bar: bool = True) -> Path:
    """Train (or skip when done) the HyperDistill student; returns its folder."""
    cfg = _config(profile)
    folder = hyperdistill_folder(out) / "student"
    if is_done(folder):
        print(f"[hyperdistill] student: skipped, already trained in {folder}")
        return folder
    teachers = hyperdistill_teachers(profile, out, progress_bar)
    robots = profile_robots(profile, "train")
    seed = profile.seed + 7
    venv = make_vec_env(
        MULTITASK_ID,
        cfg.n_envs,
        seed,
        profile.max_episode_steps,
        tasks=list(profile.teachers.tasks),
        morphologies=robots,
        **profile_env_kwargs(profile),
    )
    # raw observations in; the policy normalises each state with its task's teacher's statistics
    keys = {tuple(sorted(t.normalizer.norm_obs_keys or ())) for t in teachers.values() if t.normalizer is not None}
    if len(keys) > 1:
        raise ConfigError(
            f"the teachers normalise different observations {sorted(keys)}; the HyperDistill student normalises each "
            "state with its task's teacher's statistics and needs them alike"
        )
    statistics = dict(observation_statistics="teachers", normalized_keys=list(next(iter(keys), NORM_OBS_KEYS)))
    dataset = None
    if cfg.rollout_samples > 0:
        print(f"[hyperdistill] {cfg.rollout_samples} teacher-rollout states, {cfg.epochs} epochs of {cfg.loss} -> {folder}")
        dataset = _teacher_rollouts(folder, teachers, venv, cfg.rollout_samples, seed)
    th.manual_seed(seed)
    model = ImitationPPO(
        HyperDistillPolicy,
        venv,
        policy_kwargs=dict(cfg.policy_kwargs, task_input="index", **statistics),
        n_steps=cfg.n_steps,
        batch_size=min(cfg.batch_size, cfg.n_steps * cfg.n_envs),
        seed=seed,
        device=resolve_device(profile.device),
    )
    model.set_logger(configure(str(folder / "logs"), ["csv", "tensorboard"]))
    for index, teacher in teachers.items():
        model.policy.set_teacher_statistics(index, teacher.normalizer)
    info: dict[str, Any] = {
        "teacher_policy": cfg.teacher_policy,
        "loss": cfg.loss,
        "task_input": "index",
        "observation_statistics": "teachers",
    }
    if dataset is not None:
        history = fit_offline(
            model.policy,
            dataset,
            None,
            cfg.loss,
            cfg.epochs,
            cfg.batch_size,
            cfg.learning_rate,
            seed=seed,
            checkpoint=folder / FIT_CHECKPOINT,
            verbose=1,
        )
        info.update(offline_loss_first=history[0], offline_loss_last=history[-1], offline_samples=dataset.size)
        for epoch, value in enumerate(history):
            model.logger.record("hyperdistill/offline_loss", value)
            model.logger.dump(epoch)
    if cfg.dagger_timesteps > 0:
        print(f"[hyperdistill] DAgger for {cfg.dagger_timesteps} steps")
        callback = DAggerCallback(
            teachers,
            TASK_NAMES,
            learning_rate=cfg.learning_rate,
            epochs=cfg.dagger_epochs,
            batch_size=cfg.batch_size,
            buffer_size=cfg.buffer_size,
            seed=seed,
        )
        model.learn(cfg.dagger_timesteps, callback=callback, progress_bar=progress_bar)
    atomic_save(folder / MODEL, model.save)
    mark_done(folder, **info)
    for scratch in (ROLLOUTS, FIT_CHECKPOINT):  # gigabytes of states, not needed again
        (folder / scratch).unlink(missing_ok=True)
    return folder


def _teacher_rollouts(folder: Path, teachers: dict[int, Teacher], venv, n_samples: int, seed: int) -> TeacherRollouts:
    """The teacher-rollout states of the student in ``folder``: collected once and written there, read
    back on a resume."""
    path = folder / ROLLOUTS
    if path.is_file():
        dataset = TeacherRollouts.load(path)
        print(f"[resume] {folder}: {dataset.size} teacher-rollout states read from {path.name}")
        return dataset
    dataset = collect_teacher_rollouts(teachers, venv, n_samples, seed=seed, verbose=1)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_save(path, dataset.save)
    return dataset


def export_mlp(profile: Profile, out: Path, robot_file: Path, task: str, steps: int = 32) -> dict[str, Any]:
    """Generate, export and check the MLP of one robot x task; returns (and writes) its report."""
    if task not in TASK_NAMES:
        raise ConfigError(f"unknown task {task!r}; choose from {list(TASK_NAMES)}")
    robot_file = Path(robot_file)
    folder = hyperdistill_folder(out) / "export" / f"{robot_file.stem}-{task}"
    if is_done(folder):
        print(f"[hyperdistill] {robot_file.stem} x {task}: skipped, already exported in {folder}")
        return json.loads((folder / "report.json").read_text())
    source = hyperdistill_folder(out) / "student"
    if not is_done(source):
        raise FileNotFoundError(f"no HyperDistill student in {source}; run `divmorph hyperdistill --out {out}` first")
    if not _any_task(source) and task not in profile.teachers.tasks:
        raise ConfigError(
            f"the HyperDistill student has no teacher for {task!r} (task input / teachers' statistics: it "
            f"is written for its teachers' tasks {list(profile.teachers.tasks)})"
        )
    policy = load_student(stage_model(source), observation_space())
    statistics = stage_normalizer(source)  # none when the student holds its teachers' statistics
    normalizer = None if statistics is None else load_normalizer(statistics)
    env = gym.make(
        task_env_name(task), morphologies=[robot_file], max_episode_steps=profile.max_episode_steps, **profile_env_kwargs(profile)
    )
    rng = np.random.default_rng(profile.seed)
    try:
        first, _ = env.reset(seed=profile.seed)
        mlp = HyperDistillMLP.from_policy(policy, first, TASKS[task].observation_keys, normalizer)
        observations, obs = [first], first
        with th.no_grad():
            for _ in range(steps - 1):
                action = np.clip(mlp(*actor_inputs(obs))[0].numpy() + rng.normal(0, 0.3, 24), -1, 1).astype(np.float32)
                obs, _, terminated, truncated, _ = env.step(action)
                observations.append(obs)
                if terminated or truncated:
                    break
    finally:
        env.close()
    batch = {k: np.stack([o[k] for o in observations]) for k in first}
    folder.mkdir(parents=True, exist_ok=True)
    metadata = {
        "robot": robot_file.stem,
        "task": task,
        "source": str(source / MODEL),
        "inputs": ["proprioceptive (B,12,52)", "hfield (B,1410)", "goal (B,3)", "object (B,12)"],
        "output": "action means (B,24), 0 on padded slots; clip to [-1, 1] before env.step",
    }
    path = export_torchscript(mlp, first, folder / "mlp.pt", metadata)
    try:
        onnx_path: Path | None = export_onnx(mlp, first, folder / "mlp.onnx", metadata)
    except ImportError:  # the optional "deploy" extra (onnx) is not installed
        onnx_path = None
    with th.no_grad():
        reference = policy.get_distribution(
            policy.obs_to_tensor(batch if normalizer is None else normalizer.normalize_obs(batch))[0]
        ).distribution.mean
        exported = th.jit.load(str(path))(*actor_inputs(batch, batch=True))
    max_diff = float((reference - exported).abs().max())
    if not max_diff <= TOLERANCE:
        path.unlink()
        if onnx_path is not None:
            onnx_path.unlink()
        raise RuntimeError(
            f"exported MLP differs from the student by {max_diff:.2e} > {TOLERANCE} ({robot_file.stem}, {task}; "
            f"largest action mean {float(reference.abs().max()):.3g})"
        )
    # the teacher the student learnt from: HyperDistill's own (ModuMorph) teachers, else the run's
    own, shared = Path(out) / "hyperdistill" / "teachers" / task, Path(out) / "teachers" / task
    teacher_folder = (own if (own / MODEL).is_file() else shared) if task in profile.teachers.tasks else None
    teacher_actor = None
    if teacher_folder is not None:
        from stable_baselines3 import PPO

        teacher_actor = actor_parameter_count(PPO.load(stage_model(teacher_folder), device="cpu").policy)
    weights = mlp.stored_numbers()["weights"]
    report = {
        **metadata,
        "mlp_weights": weights,
        "student_parameters": policy.parameter_counts()["total"],
        "teacher_actor_parameters": teacher_actor,
        "reduction_vs_teacher": None if teacher_actor is None else teacher_actor / weights,
        "onnx": str(onnx_path) if onnx_path is not None else "not written (pip install 'divmorph[deploy]')",
        "max_abs_diff": max_diff,
        "checked_observations": len(observations),
        "latency_mlp_ms": batch1_latency(mlp, actor_inputs(first), profile.export.latency_repeats) * 1e3,
        "torch_threads": th.get_num_threads(),
    }
    atomic_write_json(folder / "report.json", report)
    mark_done(folder)
    return report


def hyperdistill(profile: Profile, out: Path, progress_bar: bool = True) -> list[dict[str, Any]]:
    """The whole stage: teachers (if needed), student, and the per-robot MLPs of the export section."""
    train_student(profile, out, progress_bar)
    n = profile.export.robots_per_split
    robots = profile_robots(profile, "train")[:n] + profile_robots(profile, "novel")[:n]
    reports = []
    tasks = list(profile.export.tasks)
    if not _any_task(hyperdistill_folder(out) / "student"):
        untaught = [t for t in tasks if t not in profile.teachers.tasks]
        if untaught:
            print(
                f"[hyperdistill] no MLP for {', '.join(untaught)}: the student is written per task from its teachers "
                f"(task input / teachers' statistics) and has no teacher for them"
            )
        tasks = [t for t in tasks if t in profile.teachers.tasks]
    for task in tasks:
        for robot in robots:
            reports.append(export_mlp(profile, out, robot, task))
    mark_done(hyperdistill_folder(out), exported=len(reports))
    return reports
