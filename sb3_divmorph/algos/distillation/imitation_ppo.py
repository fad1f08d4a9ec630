"""PPO that collects rollouts and leaves the learning to a distillation callback."""

from __future__ import annotations

from sb3_divmorph.algos.device_ppo import DevicePPO


class ImitationPPO(DevicePPO):
    """PPO that collects rollouts but skips its own policy-gradient update (on the batched env's
    device when it is one: :class:`~sb3_divmorph.algos.device_ppo.DevicePPO`).

    For pure distillation: a :class:`DAggerCallback` does all the learning from the rollouts this
    algorithm collects (with the student's actions, or the teachers' under a
    :class:`TeacherMixingVecEnv`). Everything else (rollouts, logging, saving, ``learn``'s progress
    bar) is PPO's.
    """

    def train(self) -> None:
        self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
