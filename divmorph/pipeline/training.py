"""Resumable PPO-family runs: checkpoints, the final model of a stage, and :class:`TrainingRun`.

Long training saves checkpoints (model + ``VecNormalize`` statistics) every ``checkpoint_every``
steps into a fresh folder and then atomically points ``checkpoints/latest.json`` at it, so a run
killed mid-way resumes from the last complete checkpoint and loses at most one interval; one
interrupted (SIGINT) saves a checkpoint where it stopped before it exits. Callbacks
with state of their own (:class:`StatefulCallback`, e.g. DAgger's aggregated dataset) save it into
the same checkpoint. A finished run continues to a larger budget from its final model (:func:`reopen`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import configure
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import VecEnv
from sb3_divmorph.algos.vec_normalize import LeanVecNormalize

import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from sb3_divmorph.algos.distillation import check_spaces

from divmorph.pipeline.envs import trained_env_settings
from divmorph.pipeline.files import DONE, ENV_SETTINGS, MODEL, NORMALIZER, atomic_save, atomic_write_json, is_done, mark_done, read_done


@runtime_checkable
class StatefulCallback(Protocol):
    """A callback whose own state belongs in checkpoints (DAgger's aggregated dataset and
    optimiser): without it a resumed run would not continue the run it resumes."""

    def save_state(self, folder: Path) -> None: ...

    def load_state(self, folder: Path) -> None: ...


class AtomicCheckpointCallback(BaseCallback):
    """Every ``every`` steps, save model + VecNormalize (+ the state of ``stateful`` callbacks) into
    ``folder/step-<n>/`` and point ``folder/latest.json`` at it (atomically); older checkpoints are
    then removed."""

    def __init__(self, folder: Path, every: int, stateful: Sequence[StatefulCallback] = ()):
        super().__init__()
        self.folder = folder
        self.every = every
        self.stateful = stateful
        self._last = 0

    def _on_training_start(self) -> None:
        self._last = self.num_timesteps

    def _on_step(self) -> bool:
        if self.num_timesteps - self._last >= self.every:
            self._last = self.num_timesteps
            save_checkpoint(self.model, self.folder, self.stateful)
        return True


class RolloutBoundary(BaseCallback):
    """The step count of the last rollout handed to learning: an interrupted run's checkpoint goes
    back to it, so that the steps of a rollout still being collected are collected again, not
    skipped, and a rollout already handed on (to the update, to DAgger's dataset) is not collected
    twice. Placed first among the callbacks, so that it counts a rollout before any other
    callback's ``_on_rollout_end`` learns from it."""

    def __init__(self):
        super().__init__()
        self.steps = 0

    def _on_training_start(self) -> None:
        self.steps = self.num_timesteps

    def _on_rollout_end(self) -> None:
        self.steps = self.num_timesteps

    def _on_step(self) -> bool:
        return True


def save_checkpoint(model: BaseAlgorithm, folder: Path, stateful: Sequence[StatefulCallback] = ()) -> Path:
    target = folder / f"step-{model.num_timesteps:012d}"
    staging = folder / f".staging-{model.num_timesteps:012d}-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    model.save(staging / MODEL)
    normalizer = model.get_vec_normalize_env()
    if normalizer is not None:
        normalizer.save(str(staging / NORMALIZER))
    for callback in stateful:
        callback.save_state(staging)
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)
    atomic_write_json(folder / "latest.json", {"folder": target.name, "num_timesteps": model.num_timesteps})
    for old in folder.glob("step-*"):
        if old != target:
            shutil.rmtree(old, ignore_errors=True)
    return target


def has_model(folder: Path) -> bool:
    """Whether a stage finished and its ``model.zip`` is in this checkout (see :func:`stage_model`)."""
    return is_done(folder) and (Path(folder) / MODEL).is_file()


def stage_model(folder: Path) -> Path:
    """The ``model.zip`` of a trained stage.

    :raises FileNotFoundError: it is not there; when the stage is finished (``done.json``), the message
        says that the model was left out of this checkout (a recorded run ships some models only, the
        rest stay in git history) and how to get it back.
    """
    path = Path(folder) / MODEL
    if path.is_file():
        return path
    if is_done(folder):
        raise FileNotFoundError(
            f"{path} is not in this checkout: {folder} finished training (done.json), but its model does not ship "
            "(the recorded runs keep the tracked files small; their README lists what ships). Restore it from git "
            f"history (`git log --oneline -- {path}` names the commit that removed it; `git checkout <that commit>^ -- {path}`) "
            "or retrain the stage (`--redo <stage>`)."
        )
    raise FileNotFoundError(f"{path}: no model; train the stage first")


def stage_normalizer(folder: Path) -> Path | None:
    """The ``VecNormalize`` statistics a finished stage saved, or ``None`` if it trained without.

    :raises FileNotFoundError: the stage recorded statistics (``done.json``) but the file is gone;
        using the model without them would silently feed it unnormalised observations.
    """
    path = Path(folder) / NORMALIZER
    recorded = read_done(folder).get("normalizer") if is_done(folder) else None
    if recorded and not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: {folder} was trained with VecNormalize statistics (done.json), and its model "
            "would act on unnormalised observations without them. Restore the file or retrain the stage."
        )
    return path if path.is_file() else None


def reopen(folder: Path) -> int | None:
    """Make a finished training run resumable from its final model, so that a larger budget
    continues it (as SB3's ``learn(..., reset_num_timesteps=False)``) instead of starting again.

    The final model and statistics (the optimiser's state is in the model file) become the run's
    latest checkpoint, then its done marker goes: a kill in between leaves it either finished or
    resumable, never lost. Returns the step it resumes from, or ``None`` when ``folder`` holds no
    finished model.
    """
    folder = Path(folder)
    if not is_done(folder) or not (folder / MODEL).is_file():
        return None
    steps = int(read_done(folder)["num_timesteps"])
    checkpoints = folder / "checkpoints"
    target = checkpoints / f"step-{steps:012d}"
    staging = checkpoints / f".staging-{steps:012d}-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    shutil.copy2(folder / MODEL, staging / MODEL)
    if (folder / NORMALIZER).is_file():
        shutil.copy2(folder / NORMALIZER, staging / NORMALIZER)
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)
    atomic_write_json(checkpoints / "latest.json", {"folder": target.name, "num_timesteps": steps})
    (folder / DONE).unlink()
    return steps


def latest_checkpoint(folder: Path) -> Path | None:
    pointer = folder / "latest.json"
    if not pointer.is_file():
        return None
    target = folder / json.loads(pointer.read_text())["folder"]
    return target if (target / MODEL).is_file() else None


@dataclass
class TrainingRun:
    """A PPO-family run writing into ``folder`` (model, statistics, logs, checkpoints)."""

    folder: Path
    total_timesteps: int
    checkpoint_every: int
    #: builds a fresh model on a fresh VecEnv
    make_model: Callable[[], BaseAlgorithm]
    #: builds the VecEnv (the same wrappers as in make_model) for resuming from a checkpoint
    make_env: Callable[[], VecEnv]
    #: the algorithm class used to load checkpoints
    algo: type[BaseAlgorithm] = PPO
    #: called on the model after it is built or loaded (e.g. transfer's per-unit learning rates)
    prepare: Callable[[BaseAlgorithm], None] | None = None
    callbacks: Sequence[BaseCallback] = ()
    device: str = "cpu"
    progress_bar: bool = True

    def run(self) -> BaseAlgorithm:
        """Train to ``total_timesteps``, resuming from the latest checkpoint; skip if done."""
        if is_done(self.folder):
            return self.load_final()
        checkpoints = self.folder / "checkpoints"
        for stale in checkpoints.glob(".staging-*"):  # a save cut short by a kill
            shutil.rmtree(stale, ignore_errors=True)
        for stale in self.folder.glob(".*.tmp*"):
            stale.unlink(missing_ok=True)
        resume = latest_checkpoint(checkpoints)
        stateful = [c for c in self.callbacks if isinstance(c, StatefulCallback)]
        if resume is not None:
            model = self._load(resume)
            for stateful_callback in stateful:
                stateful_callback.load_state(resume)
            print(f"[resume] {self.folder}: resuming from step {model.num_timesteps} of {self.total_timesteps} (checkpoint {resume.name})")
        else:
            model = self.make_model()
        if self.prepare is not None:
            self.prepare(model)
        attempt = len(list((self.folder / "logs").glob("run-*"))) if (self.folder / "logs").exists() else 0
        model.set_logger(configure(str(self.folder / "logs" / f"run-{attempt}"), ["csv", "tensorboard"]))
        remaining = self.total_timesteps - model.num_timesteps
        if remaining > 0:
            boundary = RolloutBoundary()
            callback = CallbackList([boundary, *self.callbacks, AtomicCheckpointCallback(checkpoints, self.checkpoint_every, stateful)])
            started = model.num_timesteps
            try:
                model.learn(remaining, callback=callback, reset_num_timesteps=False, progress_bar=self.progress_bar)
            except KeyboardInterrupt:
                # SIGINT: Ctrl-C, or `timeout -s INT` at the end of a lent GPU window, where a checkpoint
                # interval can be longer than the window's training: keep what was learnt since the last
                # checkpoint, at the end of the last rollout handed to learning (an interrupt inside the
                # update keeps the minibatches done so far, and the rest of that update is lost)
                model.num_timesteps = boundary.steps
                if model.num_timesteps > started:
                    saved = save_checkpoint(model, checkpoints, stateful)
                    print(
                        f"[interrupted] {self.folder}: saved at step {model.num_timesteps} ({saved.name}); the same command resumes it",
                        flush=True,
                    )
                raise
        self.save_final(model)
        return model

    def save_final(self, model: BaseAlgorithm) -> None:
        atomic_save(self.folder / MODEL, model.save)
        settings = trained_env_settings(model.get_env())
        if settings:  # so that a model copied out of its run still says what it learnt on
            atomic_write_json(self.folder / ENV_SETTINGS, settings)
        normalizer = model.get_vec_normalize_env()
        if normalizer is not None:
            atomic_save(self.folder / NORMALIZER, lambda p: normalizer.save(str(p)))
        # recorded, so that a lost statistics file is an error later, never a silent "no normalisation"
        mark_done(self.folder, num_timesteps=model.num_timesteps, normalizer=normalizer is not None)
        shutil.rmtree(self.folder / "checkpoints", ignore_errors=True)

    def load_final(self) -> BaseAlgorithm:
        model = self._load(self.folder)
        if self.prepare is not None:
            self.prepare(model)
        return model

    def _load(self, folder: Path) -> BaseAlgorithm:
        """Model + statistics saved in ``folder``, on a fresh env; a space mismatch is an error."""
        venv = self.make_env()
        data, _, _ = load_from_zip_file(folder / MODEL, device="cpu")
        if data is None:
            raise ValueError(f"{folder / MODEL} holds no model data")
        saved_space = data["observation_space"]
        check_spaces(f"checkpoint {folder}", saved_space, venv.observation_space)
        if (folder / NORMALIZER).is_file():
            venv = LeanVecNormalize.load(str(folder / NORMALIZER), venv)
        return self.algo.load(folder / MODEL, env=venv, device=self.device)
