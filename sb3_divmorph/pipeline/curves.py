"""Evaluation curves of transfer runs: deterministic returns on training and novel robots during training.

PPO's ``rollout/ep_rew_mean`` mixes exploration noise and robots seen so far; the comparison of
arms needs the same measurement for every arm: at step 0 (zero-shot), every ``eval_every`` env
steps and at the end, each robot of the training and of the novel set runs ``eval_episodes``
deterministic episodes on the run's task, with the observation statistics the model has at that
moment (not updated by the evaluation). Rows go to ``<run>/eval.csv``
(``timesteps, split, robot, episode, return, length``), rewritten atomically after every
evaluation; a resumed run first drops the rows its killed attempt wrote after the checkpoint.
"""

from __future__ import annotations

import csv
import io
from collections import defaultdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor

from sb3_divmorph.pipeline.runs import atomic_write_text

EVAL_FILE = "eval.csv"
EVAL_COLUMNS = ["timesteps", "split", "robot", "episode", "return", "length"]


def rollout_returns(
    model: BaseAlgorithm, venv: VecEnv, robots: list[Path], episodes: int, normalize=None
) -> list[dict[str, Any]]:
    """Deterministic episode returns of ``model`` on ``venv`` (one env per robot, monitored).

    :param normalize: ``obs -> obs`` applied before the policy (e.g. ``VecNormalize.normalize_obs``).
    """
    rows: list[dict[str, Any]] = []
    finished = np.zeros(len(robots), dtype=int)
    obs = venv.reset()
    while (finished < episodes).any():
        actions, _ = model.predict(normalize(obs) if normalize else obs, deterministic=True)
        obs, _, dones, infos = venv.step(actions)
        for i in np.flatnonzero(dones):
            if finished[i] < episodes:
                rows.append({"robot": robots[i].stem, "episode": int(finished[i]),
                             "return": float(infos[i]["episode"]["r"]), "length": int(infos[i]["episode"]["l"])})
                finished[i] += 1
    return rows


def robot_venv(env_name: str, robots: list[Path], max_steps: int, seed: int, **env_kwargs: Any) -> VecEnv:
    """One monitored env per robot, seeded ``seed``."""
    venv = VecMonitor(DummyVecEnv([
        (lambda robot=robot: gym.make(env_name, morphologies=[robot], max_episode_steps=max_steps, **env_kwargs)) for robot in robots
    ]))
    venv.seed(seed)
    return venv


def read_eval(path: Path) -> list[dict[str, Any]]:
    """Rows of an ``eval.csv`` with numbers parsed (empty when the file does not exist)."""
    if not path.is_file():
        return []
    with open(path) as f:
        return [{**row, "timesteps": int(row["timesteps"]), "episode": int(row["episode"]), "return": float(row["return"]),
                 "length": int(row["length"])} for row in csv.DictReader(f)]


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
    :param env_kwargs: further env arguments (e.g. a custom ``instruction``).
    """

    def __init__(self, path: Path, env_name: str, splits: dict[str, list[Path]], every: int, episodes: int,
                 max_steps: int, seed: int, **env_kwargs: Any):
        super().__init__()
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
            if split not in self._venvs:
                self._venvs[split] = robot_venv(self.env_name, robots, self.max_steps, self.seed, **self.env_kwargs)
            venv = self._venvs[split]
            venv.seed(self.seed)  # the same episodes at every evaluation
            for row in rollout_returns(self.model, venv, robots, self.episodes, normalizer.normalize_obs if normalizer else None):
                self._rows.append({"timesteps": self.num_timesteps, "split": split, **row})
        self._last = self.num_timesteps
        write_eval(self.path, self._rows)
        means = {split: np.mean([r["return"] for r in self._rows if r["split"] == split and r["timesteps"] == self.num_timesteps])
                 for split in self.splits}
        for split, value in means.items():
            self.logger.record(f"eval/{split}_return", float(value))
