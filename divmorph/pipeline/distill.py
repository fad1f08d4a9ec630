"""Stage 2 — diversion: DAgger distillation of the teachers into one DivMorph student (and the students
of the other transfer arms: the dense MetaMorph⚗ student and the ablated DivMorph students).

The student acts in ``Unimal-MultiTask-v1`` over the training tasks and morphologies (a task is
drawn per episode), each visited state is labelled by its own task's teacher, and the student
minimises ``KL(teacher || student)`` (see :mod:`sb3_divmorph.algos.distillation`). With
``ppo_loss: false`` (default) learning is pure distillation (:class:`ImitationPPO`) and the
teacher's action is executed with probability beta, annealed from ``beta_start`` to ``beta_end``;
with ``ppo_loss: true`` the distillation steps run alongside PPO's own update.

Every student (:data:`~divmorph.pipeline.students.STUDENTS`) is distilled by the same callback with the same ``distill``
settings and budget; only its policy differs:

* ``divmorph``: :class:`~sb3_divmorph.policies.DivMorphPolicy` with ``student.policy_kwargs``
  (folder ``student/``);
* ``distilled``: a dense :class:`~sb3_divmorph.policies.MetaMorphPolicy` with the teachers'
  ``policy_kwargs``. MetaMorph has no gates, so nothing in it would tell the five tasks apart: it
  reads ``task_embedding`` as one more late-fused exteroception input (an MLP of ``d_model`` width
  whose output is appended to every token, like the height map's), so one network can imitate
  five teachers and see the novel task's instruction at transfer;
* ``no-kdiv-transformer`` / ``no-kdiv-decoder`` / ``no-orthogonality``: the DivMorph student with
  ``divert_transformer`` / ``divert_decoder`` / ``orthogonal`` switched off;
* ``deploy-g4k2`` / ``deploy-g2k1`` / ``deploy-g1k1``: the DivMorph student of the same sizes with a
  named deployment diversion (:data:`~sb3_divmorph.policies.DIVERSIONS`: few learngenes, TopK 1-2,
  exteroception diverted), whose compact actors are many times smaller; the export stage measures
  what each keeps of the default student's return.

The other students live in ``students/<name>/``.
"""

from __future__ import annotations

from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.utils import LinearSchedule
from sb3_divmorph.algos.vec_normalize import LeanVecNormalize

from sb3_divmorph.algos.distillation import DAggerCallback, ImitationPPO, TeacherMixingVecEnv
from divmorph.pipeline.config import ConfigError, Profile, load_zoo_entry
from divmorph.pipeline.folders import load_teachers, student_folder
from divmorph.pipeline.envs import make_vec_env, profile_env_kwargs, resolve_device
from divmorph.pipeline.files import is_done
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import TrainingRun
from divmorph.pipeline.students import STUDENTS, StudentSpec, dense_student_kwargs  # noqa: F401 -- re-exported
from unimal_envs import MULTITASK_ID
from unimal_envs.contract import TASK_NAMES

#: Observation keys the student normalises (masks, context and embeddings must reach it as they are).
NORM_OBS_KEYS = ["proprioceptive"]


def distill_run(profile: Profile, out: Path, name: str = "divmorph", progress_bar: bool = True) -> TrainingRun:
    """The (resumable) DAgger run of student ``name`` (see :data:`~divmorph.pipeline.students.STUDENTS`)."""
    spec = STUDENTS[name]
    cfg = profile.distill
    teachers = load_teachers(profile, out)
    robots = profile_robots(profile, "train")
    device = resolve_device(profile.device)
    seed = profile.seed
    mixing = max(cfg.beta_start, cfg.beta_end) > 0
    # PPO's own settings (used only with ppo_loss) follow the FT teacher's zoo entry.
    ppo_kwargs = load_zoo_entry(profile.teachers.hyperparams, "Unimal-FT-v0", profile.teachers.overrides).ppo_kwargs
    ppo_kwargs.update(n_steps=cfg.n_steps, batch_size=cfg.batch_size)
    algo = PPO if cfg.ppo_loss else ImitationPPO
    policy_kwargs = spec.kwargs(profile)

    def make_env():
        venv = make_vec_env(
            MULTITASK_ID,
            cfg.n_envs,
            seed,
            profile.max_episode_steps,
            cfg.env_backend,
            cfg.worlds_per_robot,
            device,
            cfg.terrain_variants,
            tasks=list(profile.teachers.tasks),
            morphologies=robots,
            **profile_env_kwargs(profile),
        )
        # on the batched backend the teachers' actions are mixed in on the device (DAggerCallback with
        # DevicePPO); a VecEnv wrapper would send every step through the host
        if not mixing or cfg.env_backend == "batched":
            return venv
        return TeacherMixingVecEnv(venv, teachers, beta=cfg.beta_start, seed=seed)

    def make_model():
        venv = LeanVecNormalize(make_env(), norm_obs_keys=NORM_OBS_KEYS, norm_reward=False)
        return algo(spec.policy, venv, policy_kwargs=dict(policy_kwargs), seed=seed, device=device, **ppo_kwargs)

    callback = DAggerCallback(
        teachers,
        TASK_NAMES,
        beta=LinearSchedule(cfg.beta_start, cfg.beta_end, 1.0),
        learning_rate=cfg.learning_rate,
        epochs=cfg.epochs,
        batch_size=cfg.batch_size,
        buffer_size=cfg.buffer_size,
        seed=seed,
        load_balance=cfg.load_balance,
        target_bound=cfg.target_bound,
        weight_decay=cfg.weight_decay,
        optimizer=cfg.optimizer,
        value_weight=cfg.value_weight,
    )
    return TrainingRun(
        student_folder(out, name),
        cfg.n_timesteps,
        cfg.checkpoint_every,
        make_model,
        make_env,
        algo=algo,
        callbacks=[callback],
        device=device,
        progress_bar=progress_bar,
    )


def distill_student(profile: Profile, out: Path, name: str = "divmorph", progress_bar: bool = True) -> Path:
    """Distil the teachers into student ``name`` (resumes; skips when done); returns its folder."""
    folder = student_folder(out, name)
    if is_done(folder):
        print(f"[distill] {name}: skipped, already distilled in {folder}")
    else:
        print(f"[distill] DAgger into the {STUDENTS[name].description} for {profile.distill.n_timesteps} steps -> {folder}")
        distill_run(profile, out, name, progress_bar=progress_bar).run()
    return folder


def distill(profile: Profile, out: Path, progress_bar: bool = True, students: list[str] | None = None, backend=None) -> list[Path]:
    """Distil the profile's teachers into the DivMorph student and, by default, into the students
    the profile's transfer arms need (resumes; skips the ones done).

    :param students: these students instead (names of :data:`~divmorph.pipeline.students.STUDENTS`).
    :param backend: a :mod:`~divmorph.pipeline.grid` backend (the students are independent runs).
    :raises FileNotFoundError: the teachers are missing.
    :raises GridError: some students failed (the others finished).
    """
    from divmorph.pipeline.arms import students_for
    from divmorph.pipeline.grid import Job, run_grid

    names = list(dict.fromkeys(students if students is not None else ["divmorph", *students_for(profile.transfer.arm_list())]))
    unknown = [n for n in [*names, *profile.student.overrides] if n not in STUDENTS]
    if unknown:
        raise ConfigError(f"unknown student(s) {unknown} (--students or student.overrides); students: {list(STUDENTS)}")
    jobs = [Job(f"{__name__}:distill_run", (name,), student_folder(out, name), f"student {name}") for name in names]
    if not all(is_done(job.folder) for job in jobs):
        load_teachers(profile, out)  # a missing teacher is an error before anything starts
    for job in jobs:
        if is_done(job.folder):
            print(f"[distill] {job.args[0]}: skipped, already distilled in {job.folder}")
        else:
            print(f"[distill] DAgger into the {STUDENTS[job.args[0]].description} for {profile.distill.n_timesteps} steps -> {job.folder}")
    run_grid(profile, out, jobs, backend, progress_bar).raise_on_failure()
    return [job.folder for job in jobs]
