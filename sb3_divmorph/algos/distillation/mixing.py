"""DAgger's beta-mixture on a VecEnv: the teacher's action executed instead of the agent's with probability beta."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from sb3_divmorph.algos.distillation.labels import teacher_for
from sb3_divmorph.algos.distillation.observations import ObsDict, index_obs, task_indices
from sb3_divmorph.algos.distillation.teacher import Teacher


class TeacherMixingVecEnv(VecEnvWrapper):
    """Executes each state's teacher action instead of the agent's with probability ``beta``.

    Place it below ``VecNormalize`` so it sees raw observations. ``beta = 0`` passes actions
    through untouched. The policy's rollout buffer still records the agent's own actions, so mix
    only in pure distillation (the PPO loss would be off-policy).

    :param venv: the vectorised env (observations must carry ``task_index``).
    :param teachers: ``{task index: teacher}``.
    :param beta: initial mixing probability.
    :param seed: seed of the mixing draws.
    """

    def __init__(self, venv: VecEnv, teachers: Mapping[int, Teacher], beta: float = 0.0, seed: int | None = None):
        super().__init__(venv)
        self.teachers = dict(teachers)
        self.beta = beta
        self.rng = np.random.default_rng(seed)
        self._obs: ObsDict | None = None
        self.teacher_steps = 0

    def reset(self):
        self._obs = self.venv.reset()
        return self._obs

    def step_async(self, actions: np.ndarray) -> None:
        if self.beta > 0 and self._obs is not None:
            chosen = np.flatnonzero(self.rng.random(self.num_envs) < self.beta)
            if len(chosen):
                actions = np.array(actions, copy=True)
                tasks = task_indices(self._obs)
                for task in np.unique(tasks[chosen]):
                    rows = chosen[tasks[chosen] == task]
                    actions[rows] = teacher_for(self.teachers, int(task)).act(index_obs(self._obs, rows))
                self.teacher_steps += len(chosen)
        self.venv.step_async(actions)

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        self._obs = obs
        return obs, rewards, dones, infos
