"""Evaluation curves of transfer runs: deterministic returns on training and novel robots during training.

PPO's ``rollout/ep_rew_mean`` mixes exploration noise and robots seen so far; the comparison of
arms needs the same measurement for every arm: at step 0 (zero-shot), every ``eval_every`` env
steps and at the end, each robot of the training and of the novel set runs ``eval_episodes``
deterministic episodes on the run's task, with the observation statistics the model has at that
moment (not updated by the evaluation). Rows go to ``<run>/eval.csv``
(``timesteps, split, robot, episode, return, length``), rewritten atomically after every
evaluation; a resumed run first drops the rows its killed attempt wrote after the checkpoint.
A task's ``transfer/<task>/metrics.csv`` is made from these curves (:func:`write_metrics`).
"""

from __future__ import annotations

import csv
import io
import zlib
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv
from sb3_divmorph.algos.vec_normalize import LeanVecNormalize

from unimal_envs.vector import UnimalVecEnv

from divmorph.pipeline.arms import ARMS
from divmorph.pipeline.config import Profile
from divmorph.pipeline.metrics import ArmMetrics, RobotCurves, task_metrics_from_curves
from divmorph.pipeline.envs import task_env_name
from divmorph.pipeline.files import atomic_write_text, is_done, read_csv_rows, write_csv
from divmorph.pipeline.batched_evaluation import batched_returns, make_evaluation_env
from divmorph.pipeline.robots import SPLITS, trained_env_kwargs
from divmorph.pipeline.training import stage_model, stage_normalizer

EVAL_FILE = "eval.csv"
EVAL_COLUMNS = ["timesteps", "split", "robot", "episode", "return", "length"]


def rollout_returns(
    model: BaseAlgorithm, venv: VecEnv, robots: list[Path], episodes: int, normalize=None, deterministic: bool = True
) -> list[dict[str, Any]]:
    """Episode returns of ``model`` on ``venv`` (one env per robot, monitored), in the order of
    ``robots`` and, per robot, of its episodes (not the order they finish in).

    :param normalize: ``obs -> obs`` applied before the policy (e.g. ``VecNormalize.normalize_obs``).
    :param deterministic: the policy's mean action (the default); ``False`` samples as in training.
    """
    rows: list[dict[str, Any]] = []
    places: list[tuple[int, int]] = []  # (robot, episode) of each row, to sort them by at the end
    finished = np.zeros(len(robots), dtype=int)
    obs = venv.reset()
    while (finished < episodes).any():
        actions, _ = model.predict(normalize(obs) if normalize else obs, deterministic=deterministic)  # type: ignore[arg-type]  # VecEnv obs: a dict here
        obs, _, dones, infos = venv.step(actions)
        for i in np.flatnonzero(dones):
            if finished[i] < episodes:
                rows.append(
                    {
                        "robot": robots[i].stem,
                        "episode": int(finished[i]),
                        "return": float(infos[i]["episode"]["r"]),
                        "length": int(infos[i]["episode"]["l"]),
                    }
                )
                places.append((int(i), int(finished[i])))
                finished[i] += 1
    return [row for _, row in sorted(zip(places, rows), key=lambda pair: pair[0])]


def episode_seed(seed: int, robot: str | Path, episode: int) -> int:
    """The reset seed of episode ``episode`` of ``robot`` under evaluation seed ``seed``: the project's
    one rule for "a seed gives an episode".

    A hash of all three (:class:`numpy.random.SeedSequence`), so that (1) a robot's episode does not
    depend on the robots evaluated beside it, (2) the robots of one evaluation draw *different*
    episodes -- on PointNav, Escape or Exploration different goals and terrains, not the same few
    for every robot -- and (3) two evaluation seeds share no episode (``seed + e`` made episode 1 of
    seed 0 the episode 0 of seed 1).

    :param robot: the robot's name or its MJCF file.
    """
    name = Path(robot).name.removesuffix(".xml")
    return int(np.random.SeedSequence([int(seed), zlib.crc32(name.encode()), int(episode)]).generate_state(1)[0])


class EpisodeSeeds(gym.Wrapper):
    """Seeds each episode of one robot's env: episode ``e`` under seed ``s`` is
    ``reset(seed=episode_seed(s, robot, e))``.

    :func:`robot_venv` (the evaluation, the curves, :meth:`~divmorph.pretrained.Pretrained.evaluate`),
    ``divmorph record`` and the examples all play episode ``e`` of robot ``R`` under seed ``s`` so --
    an episode seen in a table can be filmed, whatever other robots ran beside it. (A reset of the
    multi-robot env with ``options={"morphology": R}`` starts the same episode as a reset of an env
    holding only ``R``.)

    :param robot: the robot this env runs (its name or file).
    """

    def __init__(self, env: gym.Env, seed: int, robot: str | Path):
        super().__init__(env)
        self.first_seed = int(seed)
        self.robot = Path(robot).name.removesuffix(".xml")
        self.episode = 0

    def rewind(self) -> None:
        """The next reset starts episode 0 again (the same episodes at every evaluation)."""
        self.episode = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:  # an explicit seed restarts the count from it
            self.first_seed, self.episode = int(seed), 0
        reset_seed = episode_seed(self.first_seed, self.robot, self.episode)
        self.episode += 1
        return self.env.reset(seed=reset_seed, options=options)


def robot_venv(env_name: str, robots: list[Path], max_steps: int, seed: int, **env_kwargs: Any) -> VecEnv:
    """One env per robot, its episodes seeded by :class:`EpisodeSeeds` (:func:`episode_seed`), in one
    :class:`~unimal_envs.vector.UnimalVecEnv` (episode statistics as VecMonitor's)."""

    def one(robot: Path) -> Callable[[], gym.Env]:
        return lambda: EpisodeSeeds(gym.make(env_name, morphologies=[robot], disable_env_checker=True, **env_kwargs).unwrapped, seed, robot)

    return UnimalVecEnv([one(robot) for robot in robots], max_steps)


def rewind(venv: VecEnv) -> None:
    """Start a :func:`robot_venv`'s episodes again from episode 0 (its next reset)."""
    venv.env_method("rewind")


def read_eval(path: Path) -> list[dict[str, Any]]:
    """Rows of an ``eval.csv`` (or its packed ``eval.csv.gz``) with numbers parsed (empty when there is none)."""
    return [
        {
            **row,
            "timesteps": int(row["timesteps"]),
            "episode": int(row["episode"]),
            "return": float(row["return"]),
            "length": int(row["length"]),
        }
        for row in read_csv_rows(path)
    ]


def write_eval(path: Path, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=EVAL_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())


def eval_curve(rows: list[dict[str, Any]], split: str) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, mean return over robots and episodes)`` of one split, by step."""
    by_step: dict[int, list[float]] = defaultdict(list)
    for row in rows:
        if row["split"] == split:
            by_step[row["timesteps"]].append(row["return"])
    steps = np.array(sorted(by_step), dtype=float)
    return steps, np.array([np.mean(by_step[int(s)]) for s in steps])


class EvalCurveCallback(BaseCallback):
    """Deterministic evaluation on several robot sets at step 0, every ``every`` steps and at the end.

    :param path: the ``eval.csv`` to write.
    :param env_name: the task's env id.
    :param splits: ``{split name: robots}`` (e.g. ``train`` and ``novel``).
    :param every: env steps between evaluations.
    :param episodes: episodes per robot.
    :param max_steps: episode length limit.
    :param seed: seed of the evaluation envs (the same at every evaluation).
    :param backend: ``single``: each robot's episodes in turn in a C-MuJoCo env of its own
        (:func:`robot_venv`); ``batched``: all of them at once, one MuJoCo Warp world per episode on
        ``device`` (:mod:`~divmorph.pipeline.batched_evaluation`; the same episodes at every
        evaluation, but not the single env's).
    :param device: where the batched evaluation runs.
    :param terrain_variants: the batched evaluation's terrain pool per split.
    :param env_kwargs: further env arguments (e.g. a custom ``instruction``).
    """

    def __init__(
        self,
        path: Path,
        env_name: str,
        splits: dict[str, list[Path]],
        every: int,
        episodes: int,
        max_steps: int,
        seed: int,
        backend: str = "single",
        device: str = "cpu",
        terrain_variants: int = 64,
        **env_kwargs: Any,
    ):
        super().__init__()
        if backend not in ("single", "batched"):
            raise ValueError(f"the evaluation backend must be 'single' or 'batched', got {backend!r}")
        self.backend, self.device, self.terrain_variants = backend, device, terrain_variants
        self.path = Path(path)
        self.env_name = env_name
        self.splits = {name: list(robots) for name, robots in splits.items() if robots}
        self.every = every
        self.episodes = episodes
        self.max_steps = max_steps
        self.seed = seed
        self.env_kwargs = env_kwargs
        self._venvs: dict[str, VecEnv] = {}
        self._rows: list[dict[str, Any]] = []
        self._last = -1

    def _on_training_start(self) -> None:
        # rows beyond the resumed checkpoint belong to the killed attempt's lost steps
        self._rows = [row for row in read_eval(self.path) if row["timesteps"] <= self.num_timesteps]
        recorded = {row["timesteps"] for row in self._rows}
        if self.num_timesteps in recorded:
            self._last = self.num_timesteps
        else:
            self.evaluate()

    def _on_step(self) -> bool:
        if self.num_timesteps - self._last >= self.every:
            self.evaluate()
        return True

    def _on_training_end(self) -> None:
        if self._last != self.num_timesteps:
            self.evaluate()
        for venv in self._venvs.values():
            venv.close()
        self._venvs = {}

    def evaluate(self) -> None:
        """Evaluate the current model on every split and rewrite ``eval.csv``."""
        normalizer = self.model.get_vec_normalize_env()
        for split, robots in self.splits.items():
            if self.backend == "batched":
                if split not in self._venvs:
                    self._venvs[split] = make_evaluation_env(
                        self.env_name,
                        robots,
                        self.episodes,
                        self.max_steps,
                        self.seed,
                        self.device,
                        self.terrain_variants,
                        **self.env_kwargs,
                    )
                for row in batched_returns(self.model, self._venvs[split], normalizer, self.seed):
                    self._rows.append({"timesteps": self.num_timesteps, "split": split, **row})
                continue
            if split not in self._venvs:
                self._venvs[split] = robot_venv(self.env_name, robots, self.max_steps, self.seed, **self.env_kwargs)
            venv = self._venvs[split]
            rewind(venv)  # the same episodes at every evaluation
            for row in rollout_returns(self.model, venv, robots, self.episodes, normalizer.normalize_obs if normalizer else None):
                self._rows.append({"timesteps": self.num_timesteps, "split": split, **row})
        self._last = self.num_timesteps
        write_eval(self.path, self._rows)
        means = {
            split: np.mean([r["return"] for r in self._rows if r["split"] == split and r["timesteps"] == self.num_timesteps])
            for split in self.splits
        }
        for split, value in means.items():
            self.logger.record(f"eval/{split}_return", float(value))


# -- a task's transfer metrics, from its runs' curves ------------------------------------------------
def seed_curves(out: Path, task: str, arm: str, split: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{seed: (steps, mean return)}`` of every seed of an arm with an evaluation curve."""
    base = Path(out) / "transfer" / task / arm
    folders = {int(folder.name.split("-")[1]): folder for folder in base.glob("seed-*")}
    folders.setdefault(0, base)  # a run in the arm's folder itself (no seed-<n>/) is seed 0
    curves = {}
    for seed, folder in sorted(folders.items()):
        steps, returns = eval_curve(read_eval(folder / EVAL_FILE), split)
        if len(steps):
            curves[seed] = (steps, returns)
    return curves


def seed_robot_curves(out: Path, task: str, arm: str, split: str, finished_only: bool = False) -> dict[int, RobotCurves]:
    """``{seed: RobotCurves}`` (per robot and step, mean over episodes) of every seed of an arm with an evaluation curve.

    :param finished_only: leave out the seeds whose run has not finished (``done.json``): a run still
        going has a shorter curve, and the metrics compare every seed over the steps all of them reached.
    """
    base = Path(out) / "transfer" / task / arm
    folders = {int(folder.name.split("-")[1]): folder for folder in base.glob("seed-*")}
    folders.setdefault(0, base)  # a run in the arm's folder itself (no seed-<n>/) is seed 0
    curves = {}
    for seed, folder in sorted(folders.items()):
        if finished_only and not is_done(folder):
            continue
        found = RobotCurves.from_rows(read_eval(folder / EVAL_FILE), split)
        if len(found.steps) and found.robots:
            curves[seed] = found
    return curves


def task_metrics(profile: Profile, out: Path, task: str) -> list[ArmMetrics]:
    """Metrics of every arm with finished runs on ``task``, every robot split with curves (see :mod:`~divmorph.pipeline.metrics`)."""
    metrics = []
    for split in SPLITS:
        runs = {arm: list(curves.values()) for arm in ARMS if (curves := seed_robot_curves(out, task, arm, split, finished_only=True))}
        if runs:
            metrics += task_metrics_from_curves(task, split, runs)
    return metrics


METRIC_COLUMNS = [
    "task",
    "arm",
    "split",
    "seeds",
    "robots",
    "zero_shot",
    "zero_shot_sd",
    "zero_shot_lo",
    "zero_shot_hi",
    "final",
    "final_sd",
    "final_lo",
    "final_hi",
    "auc",
    "auc_sd",
    "auc_lo",
    "auc_hi",
    "level",
    "steps_to_level",
    "steps_lo",
    "steps_hi",
    "held",
    "sample_efficiency",
    "budget",
]


def write_metrics(profile: Profile, out: Path, task: str) -> list[ArmMetrics]:
    """Write ``transfer/<task>/metrics.csv`` (when there are runs) and return its rows.

    ``steps_to_level`` is empty where the arm does not hold the level, ``steps_hi`` ``inf`` where some
    bootstrap draws never do; ``sample_efficiency`` is the speed-up vs scratch in words
    (:meth:`~divmorph.pipeline.metrics.ArmMetrics.efficiency_text`).
    """
    metrics = task_metrics(profile, out, task)
    if not metrics:
        return []  # no runs of this task: no file (a run folder without transfers stays without them)
    rows = [{**{k: getattr(m, k) for k in METRIC_COLUMNS if hasattr(m, k)}, "sample_efficiency": m.efficiency_text()} for m in metrics]
    write_csv(Path(out) / "transfer" / task / "metrics.csv", rows, METRIC_COLUMNS)
    return metrics


def evaluate_model(
    folder: Path,
    task: str,
    robots: list[Path],
    episodes: int,
    max_steps: int,
    seed: int,
    instruction: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    deterministic: bool = True,
) -> list[dict[str, Any]]:
    """Returns of the model saved in ``folder`` on each robot doing ``task`` (deterministic by default).

    :param instruction: the task's instruction in other words (default: the built-in one).
    :param env_kwargs: further env arguments; default: those the model's run trained with
        (:func:`~divmorph.pipeline.robots.trained_env_kwargs`), so that it sees the observations it learnt on.
    :param deterministic: ``False`` samples actions from the policy, as training does.
    """
    if env_kwargs is None:
        env_kwargs = trained_env_kwargs(folder)
    venv = robot_venv(task_env_name(task), robots, max_steps, seed, **({"instruction": instruction} if instruction else {}), **env_kwargs)
    statistics = stage_normalizer(folder)
    if statistics is not None:
        venv = LeanVecNormalize.load(str(statistics), venv)
        venv.training, venv.norm_reward = False, False
    model = PPO.load(stage_model(folder), device="cpu")
    rows = rollout_returns(model, venv, robots, episodes, deterministic=deterministic)
    venv.close()
    return [{"morphology": row.pop("robot"), **row} for row in rows]
