"""What every pipeline stage shares: atomic outputs, envs, and resumable PPO runs.

A stage's output folder is *done* once its ``done.json`` exists; that file is written last and
atomically, so a stage killed at any point is either done or not. Long training saves checkpoints
(model + ``VecNormalize`` statistics) every ``checkpoint_every`` steps into a fresh folder and then
atomically points ``checkpoints/latest.json`` at it, so a run killed mid-way resumes from the last
complete checkpoint and loses at most one interval. Callbacks with state of their own
(:class:`StatefulCallback`, e.g. DAgger's aggregated dataset) save it into the same checkpoint.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import io
import json
import os
import shutil
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import configure
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor, VecNormalize

import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from unimal_envs import env_id
from unimal_envs.morphology.errors import MorphologyError
from unimal_envs.morphology.loader import is_set_name, morphology_files
from sb3_divmorph.distillation import check_spaces
from sb3_divmorph.finetune import freeze_observation_statistics
from sb3_divmorph.pipeline.config import ConfigError, Profile, resolve_path

DONE = "done.json"
MODEL = "model.zip"
NORMALIZER = "vecnormalize.pkl"
#: Beside every model the pipeline saves: the env settings and robots it trained with, read from its envs.
ENV_SETTINGS = "env.json"


# -- atomic files ----------------------------------------------------------------------------
def _umask() -> int:
    """The process umask (reading it means setting it; it is put back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        # mkstemp creates the file 0600; results are for sharing, so give it the mode open() would
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def atomic_save(path: Path, save: Callable[[Path], None]) -> None:
    """Call ``save(tmp_path)`` (e.g. ``model.save``) then move the result onto ``path`` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        save(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def is_done(folder: Path) -> bool:
    return (folder / DONE).is_file()


def mark_done(folder: Path, **info: Any) -> None:
    atomic_write_json(folder / DONE, {"finished": time.strftime("%Y-%m-%d %H:%M:%S"), **info})


def read_done(folder: Path) -> dict[str, Any]:
    return json.loads((folder / DONE).read_text())


# -- robots and envs -------------------------------------------------------------------------
def robot_files(robot_set: str, count: int | None, exclude: Sequence[Path] = ()) -> list[Path]:
    """The first ``count`` robots of a set (all when ``None``), leaving out the files in ``exclude``.

    :param robot_set: a set name (shipped ``train``/``novel`` or official ``unimals100-*``, fetched
        once) or a directory (relative paths also from the repository root)
    """
    source: str | Path = robot_set if is_set_name(robot_set) else resolve_path(robot_set)
    excluded = {p.resolve() for p in exclude}
    files = [f for f in morphology_files(source) if f.resolve() not in excluded]
    return files if count is None else files[:count]


#: The robot splits of a run: the robots it trains on, the novel robots of zero-shot evaluation, and
#: an out-of-distribution set reported apart (only when the profile names an ``ood_set``).
SPLITS = ("train", "novel", "ood")


def profile_splits(profile: Profile) -> tuple[str, ...]:
    """The robot splits a profile evaluates on: ``train``, ``novel`` and, with an ``ood_set``, ``ood``."""
    return SPLITS if profile.ood_set is not None else SPLITS[:2]


def profile_robots(profile: Profile, split: str) -> list[Path]:
    """The profile's ``train``, ``novel`` or ``ood`` robots; the other splits never include a training robot.

    :raises ValueError: an unknown split, or ``ood`` in a profile without an ``ood_set``.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown robot split {split!r}; choose from {list(SPLITS)}")
    train = robot_files(profile.train_set, profile.train_robots)
    if split == "train":
        return train
    if split == "ood":
        if profile.ood_set is None:
            raise ValueError(f"profile {profile.name!r} has no out-of-distribution robots (ood_set)")
        return robot_files(profile.ood_set, profile.ood_robots, exclude=train)
    return robot_files(profile.novel_set, profile.novel_robots, exclude=train)


def transfer_eval_robots(profile: Profile, split: str) -> list[Path]:
    """The robots of ``split`` that the transfer runs' evaluation curves roll out: ``transfer.eval_robots``
    of :func:`profile_robots`, spread evenly over its sorted list from the first to the last (every
    robot when it is ``None``).

    Spread, not the first ones: robot files sort by family, and a prefix stands for one family only
    (the first 20 of the official 100 are all ``floor-*`` robots, on which the cpu100 FT teacher
    returns 46 against 583 over all 100).
    """
    robots = profile_robots(profile, split)
    wanted = profile.transfer.eval_robots
    if wanted is None or wanted >= len(robots):
        return robots
    return [robots[i] for i in np.linspace(0, len(robots) - 1, wanted).round().astype(int)]


#: The record of which robots a run trains and evaluates on (at the run folder's root).
ROBOT_SETS = "robot_sets.json"


def trained_robots(folder: str | Path) -> list[Path] | None:
    """The robots a pipeline model was trained on: the ``train`` robots of the run it belongs to,
    read from the nearest ``robot_sets.json`` in ``folder`` or above it (``None`` when there is none,
    e.g. an rl-zoo run). A shipped model then runs on its own robots by default, wherever they live
    on this machine (a set name resolves to this machine's fetched copy).

    :param folder: a model folder (``teachers/FT``, ``student``, ``transfer/<task>/<arm>/seed-0``) or a
        ``model.zip`` inside one.
    :raises ConfigError: the record names robots that its set does not hold here.
    """
    record = _robot_sets_record(folder)
    if record is None:
        return None
    entry = json.loads(record.read_text())["train"]
    available = {f.stem: f for f in robot_files(entry["set"], None)}
    missing = [name for name in entry["robots"] if name not in available]
    if missing:
        raise ConfigError(
            f"{record} names robots of the set {entry['set']!r} that are not there on this machine: "
            f"{missing[:3]}{'...' if len(missing) > 3 else ''}"
        )
    return [available[name] for name in entry["robots"]]


def trained_robot_set(folder: str | Path) -> str | None:
    """The name (or folder) of the robot set a pipeline model was trained on (see :func:`trained_robots`)."""
    record = _robot_sets_record(folder)
    return None if record is None else json.loads(record.read_text())["train"]["set"]


def trained_env_kwargs(folder: str | Path) -> dict[str, Any]:
    """The env arguments the run a pipeline model belongs to made its envs with
    (:func:`profile_env_kwargs` of the profile in the nearest ``run.json`` in ``folder`` or above it;
    empty for an rl-zoo run or a run at the defaults).

    :param folder: a model folder or a ``model.zip`` inside one.
    """
    folder = Path(folder).resolve()
    if folder.suffix == ".zip":
        folder = folder.parent
    record = next((d / "run.json" for d in (folder, *folder.parents) if (d / "run.json").is_file()), None)
    if record is None:
        return {}
    height = json.loads(record.read_text()).get("configuration", {}).get("height_reference", "world")
    return {} if height == "world" else {"height_reference": height}


def _robot_sets_record(folder: str | Path) -> Path | None:
    """The nearest ``robot_sets.json`` in ``folder`` (a model folder or a ``model.zip``) or above it."""
    folder = Path(folder).resolve()
    if folder.suffix == ".zip":
        folder = folder.parent
    return next((d / ROBOT_SETS for d in (folder, *folder.parents) if (d / ROBOT_SETS).is_file()), None)


def robot_set_record(profile: Profile) -> dict[str, Any]:
    """Which robot sets a profile uses, resolved: names, folders, robot counts and, for the official
    sets, the source and checksum manifest they were fetched with (so results name their robots)."""
    record: dict[str, Any] = {}
    for split, name in (("train", profile.train_set), ("novel", profile.novel_set), ("ood", profile.ood_set)):
        if name is None:
            continue
        try:
            files = profile_robots(profile, split)
        except MorphologyError as error:
            if split == "train":
                raise
            # a stage that only trains (a GPU job carrying the training robots) needs no held-out set;
            # the evaluation that does reads it then and fails with the fetch command
            record[split] = {"set": name, "not_on_this_machine": str(error)}
            continue
        folder = files[0].parent.parent if files[0].parent.name == "xml" else files[0].parent
        # Where the set was read on this machine, with the home folder as ~ (no user's paths in results).
        entry: dict[str, Any] = {"set": name, "folder": _portable(folder), "robots": [f.stem for f in files]}
        manifest = folder / "MANIFEST.json"
        if manifest.is_file():
            data = json.loads(manifest.read_text())
            entry["source"] = data.get("source")
            entry["manifest_sha256"] = hashlib.sha256(manifest.read_bytes()).hexdigest()
        record[split] = entry
    return record


def record_robot_sets(profile: Profile, out: Path) -> Path:
    """Write :func:`robot_set_record` to ``out/robot_sets.json`` (atomically) and return its path."""
    path = Path(out) / ROBOT_SETS
    atomic_write_json(path, robot_set_record(profile))
    return path


def make_vec_env(
    env_name: str,
    n_envs: int,
    seed: int,
    max_episode_steps: int,
    backend: str = "single",
    worlds_per_robot: int = 16,
    device: str = "cpu",
    terrain_variants: int = 64,
    **env_kwargs: Any,
) -> VecEnv:
    """The monitored training envs of a stage.

    ``backend="single"``: ``n_envs`` C-MuJoCo envs in one process (torch stays in this process),
    seeded ``seed + i``. ``backend="batched"``: one MuJoCo Warp env with ``worlds_per_robot`` worlds
    of every robot on ``device`` and a pool of ``terrain_variants`` terrains per terrain task
    (:func:`unimal_envs.batched.make_batched_env`; ``n_envs`` unused).
    """
    if backend == "batched":
        from unimal_envs.batched import make_batched_env

        task = env_name.removeprefix("Unimal-").removesuffix("-v0")
        return VecMonitor(
            make_batched_env(
                task,
                worlds_per_robot=worlds_per_robot,
                device=device,
                seed=seed,
                terrain_variants=terrain_variants,
                max_episode_steps=max_episode_steps,
                **env_kwargs,
            )
        )

    def factory(rank: int) -> Callable[[], gym.Env]:
        def make() -> gym.Env:
            env = gym.make(env_name, max_episode_steps=max_episode_steps, **env_kwargs)
            env.reset(seed=seed + rank)
            return env

        return make

    venv = VecMonitor(DummyVecEnv([factory(i) for i in range(n_envs)]))
    venv.seed(seed)
    return venv


def profile_env_kwargs(profile: Profile) -> dict[str, Any]:
    """The env arguments every env of a run takes from its profile (``height_reference``); empty at
    the defaults, so envs and backends that predate them are made exactly as before."""
    return {} if profile.height_reference == "world" else {"height_reference": profile.height_reference}


def task_env_name(task: str) -> str:
    return env_id(task)


def resolve_device(device: str) -> str:
    """The torch device a profile's ``device`` resolves to on this machine.

    :raises ConfigError: ``cuda`` requested where no CUDA device exists (training would otherwise
        silently run on the CPU while the records said cuda).
    """
    if device == "auto":
        return "cuda" if th.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not th.cuda.is_available():
        raise ConfigError(f"device {device!r} requested but this machine has no CUDA device; use cpu or auto")
    return device


# -- resumable training ----------------------------------------------------------------------
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
            for callback in stateful:
                callback.load_state(resume)
            print(f"[resume] {self.folder}: resuming from step {model.num_timesteps} of {self.total_timesteps} (checkpoint {resume.name})")
        else:
            model = self.make_model()
        if self.prepare is not None:
            self.prepare(model)
        attempt = len(list((self.folder / "logs").glob("run-*"))) if (self.folder / "logs").exists() else 0
        model.set_logger(configure(str(self.folder / "logs" / f"run-{attempt}"), ["csv", "tensorboard"]))
        remaining = self.total_timesteps - model.num_timesteps
        if remaining > 0:
            callback = CallbackList([*self.callbacks, AtomicCheckpointCallback(checkpoints, self.checkpoint_every, stateful)])
            model.learn(remaining, callback=callback, reset_num_timesteps=False, progress_bar=self.progress_bar)
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
        saved_space = load_from_zip_file(folder / MODEL, device="cpu")[0]["observation_space"]
        check_spaces(f"checkpoint {folder}", saved_space, venv.observation_space)
        if (folder / NORMALIZER).is_file():
            venv = VecNormalize.load(str(folder / NORMALIZER), venv)
        return self.algo.load(folder / MODEL, env=venv, device=self.device)


def trained_env_settings(venv: VecEnv | None) -> dict[str, Any]:
    """What a model's envs were made with, read from the envs themselves: the observation setting
    ``height_reference`` and the robots (names of the first env's robots); empty when the envs do
    not tell (the batched backend, a foreign env)."""
    if venv is None:
        return {}
    try:
        height = venv.get_attr("height_reference")[0]
        robots = [m.name for m in venv.get_attr("morphologies")[0]]
    except (AttributeError, IndexError, TypeError):
        return {}
    return {"height_reference": height, "robots": robots}


def normalizer_for(venv: VecEnv, normalize: dict[str, Any] | None, gamma: float) -> VecEnv:
    """Wrap in ``VecNormalize`` with rl-zoo's ``normalize`` kwargs (``None``: no normalisation)."""
    if normalize is None:
        return venv
    return VecNormalize(venv, gamma=gamma, **normalize)


def seed_everything(seed: int, threads: int) -> None:
    th.set_num_threads(max(1, threads))
    np.random.seed(seed)
    th.manual_seed(seed)


# -- logs that ship packed -----------------------------------------------------------------
# A recorded run ships its finished stages' CSV logs gzip-compressed (``progress.csv.gz``,
# ``eval.csv.gz``, ``returns.csv.gz``: benchmarks/pack_logs.py) to keep the repository small; every
# reader takes either form, and a plain file, written later, wins over its packed twin.
def log_file(path: Path) -> Path | None:
    """``path`` if it exists, else its packed twin ``<path>.gz`` if that exists, else ``None``."""
    path = Path(path)
    packed = path.with_name(path.name + ".gz")
    return path if path.is_file() else packed if packed.is_file() else None


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """The rows of the CSV ``path`` or of its packed twin (empty when there is neither); ``path`` may
    name the packed file itself (as :func:`log_files` gives it)."""
    path = Path(path)
    found = path if path.suffix == ".gz" and path.is_file() else log_file(path)
    if found is None:
        return []
    with gzip.open(found, "rt", newline="") if found.suffix == ".gz" else open(found, newline="") as f:
        return list(csv.DictReader(f))


def log_files(folder: Path, pattern: str) -> list[Path]:
    """The CSV logs ``folder.glob(pattern)`` finds, each in the form :func:`log_file` reads (a file
    and its packed twin count once)."""
    names = {p.with_suffix("") if p.suffix == ".gz" else p for p in (*folder.glob(pattern), *folder.glob(pattern + ".gz"))}
    return [found for name in sorted(names) if (found := log_file(name)) is not None]


def read_progress(folder: Path) -> dict[str, np.ndarray]:
    """All ``progress.csv`` rows of a training run (resumed attempts concatenated), by column."""
    rows: list[dict[str, str]] = []
    for log in sorted(log_files(folder / "logs", "run-*/progress.csv"), key=lambda p: int(p.parent.name.split("-")[1])):
        rows += read_csv_rows(log)
    columns: dict[str, list[float]] = defaultdict(list)
    keys = {k for row in rows for k in row}
    for row in rows:
        for key in keys:
            value = row.get(key, "")
            columns[key].append(float(value) if value not in ("", None) else np.nan)
    return {k: np.asarray(v) for k, v in columns.items()}


def _portable(path: Path) -> str:
    """``path`` as another machine can read it: relative to the repository when inside it (the
    shipped sets), else with the user's home folder written as ``~`` (the fetched official sets)."""
    path = path.resolve()
    for base, shown in ((Path(__file__).resolve().parents[2], None), (Path.home(), Path("~"))):
        try:
            relative = path.relative_to(base)
        except ValueError:
            continue
        return str(relative if shown is None else shown / relative)
    return str(path)


def robot_observations(
    env_name: str, robots: list[Path], seed: int = 0, instruction: str | None = None, **env_kwargs: Any
) -> dict[str, np.ndarray]:
    """One reset observation per robot, batched (for gates and selections).

    :param env_kwargs: further env arguments (e.g. the run's ``height_reference``).
    """
    import gymnasium as gym

    env = gym.make(env_name, morphologies=robots, **({"instruction": instruction} if instruction else {}), **env_kwargs)
    try:
        observations = [env.reset(seed=seed, options={"morphology": i})[0] for i in range(len(robots))]
    finally:
        env.close()
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


def inherited_normalizer(source: Path, venv: VecEnv, gamma: float, freeze_observations: bool = False) -> VecEnv:
    """``venv`` wrapped in the observation statistics saved in ``source`` (if any); rewards are
    normalised afresh for the new task (their statistics learn).

    :param source: the folder of the trained model whose ``vecnormalize.pkl`` is inherited.
    :param venv: the new task's envs.
    :param gamma: the new run's discount (for the reward statistics).
    :param freeze_observations: keep the observation statistics exactly as inherited
        (:func:`~sb3_divmorph.finetune.freeze_observation_statistics`): transfer does, so that the
        inputs of the weights it starts from do not move under them. ``False`` (GRL's evolution,
        where a child trains every layer on a training task) lets them go on learning.
    """
    if not (source / NORMALIZER).is_file():
        return venv
    normalizer = VecNormalize.load(str(source / NORMALIZER), venv)
    normalizer.training, normalizer.norm_reward = True, True
    normalizer.gamma = gamma
    normalizer.ret_rms = RunningMeanStd(shape=())
    normalizer.returns = np.zeros(venv.num_envs)
    if freeze_observations:
        freeze_observation_statistics(normalizer)
    return normalizer


def write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str]) -> None:
    """Write ``rows`` (dicts) as a CSV with these ``columns``, atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())
