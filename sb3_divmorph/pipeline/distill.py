"""Stage 2 — diversion: DAgger distillation of the teachers into one DivMorph student.

The student acts in ``Unimal-MultiTask-v0`` over the training tasks and morphologies (a task is
drawn per episode), each visited state is labelled by its own task's teacher, and the student
minimises ``KL(teacher || student)`` (see :mod:`sb3_divmorph.distillation`). With
``ppo_loss: false`` (default) learning is pure distillation (:class:`ImitationPPO`) and the
teacher's action is executed with probability beta, annealed from ``beta_start`` to ``beta_end``;
with ``ppo_loss: true`` the distillation steps run alongside PPO's own update.
"""

from __future__ import annotations

from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.utils import LinearSchedule
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.distillation import DAggerCallback, ImitationPPO, TeacherMixingVecEnv
from sb3_divmorph.pipeline.config import Profile, load_zoo_entry
from sb3_divmorph.pipeline.runs import TrainingRun, is_done, make_vec_env, profile_robots, resolve_device
from sb3_divmorph.pipeline.teachers import load_teachers
from sb3_divmorph.policies import DivMorphPolicy
from unimal_envs.contract import TASK_NAMES

#: Observation keys the student normalises (masks, context and embeddings must reach it as they are).
NORM_OBS_KEYS = ["proprioceptive"]


def student_folder(out: Path) -> Path:
    return Path(out) / "student"


def distill_run(profile: Profile, out: Path, progress_bar: bool = True) -> TrainingRun:
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

    def make_env():
        venv = make_vec_env(
            "Unimal-MultiTask-v0", cfg.n_envs, seed, profile.max_episode_steps,
            tasks=list(profile.teachers.tasks), morphologies=robots,
        )
        return TeacherMixingVecEnv(venv, teachers, beta=cfg.beta_start, seed=seed) if mixing else venv

    def make_model():
        venv = VecNormalize(make_env(), norm_obs_keys=NORM_OBS_KEYS, norm_reward=False)
        return algo(DivMorphPolicy, venv, policy_kwargs=dict(profile.student.policy_kwargs), seed=seed, device=device, **ppo_kwargs)

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
    )
    return TrainingRun(
        student_folder(out), cfg.n_timesteps, cfg.checkpoint_every, make_model, make_env,
        algo=algo, callbacks=[callback], device=device, progress_bar=progress_bar,
    )


def distill(profile: Profile, out: Path, progress_bar: bool = True):
    """Distil the profile's teachers into a DivMorph student (resumes; skips when done)."""
    if is_done(student_folder(out)):
        print(f"[distill] skipped, already distilled in {student_folder(out)}")
        return None
    print(f"[distill] DAgger into a DivMorph student for {profile.distill.n_timesteps} steps -> {student_folder(out)}")
    return distill_run(profile, out, progress_bar).run()
