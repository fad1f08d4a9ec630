"""A distillation teacher: a trained policy with the observation normalisation it was trained under."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.device_ppo import DeviceNormalizer
from sb3_divmorph.algos.distillation.normalizer import load_normalizer
from sb3_divmorph.algos.distillation.observations import ObsDict
from sb3_divmorph.algos.distillation.space_checks import check_spaces


@dataclass
class Teacher:
    """A trained policy and the observation normalisation it saw during training.

    :param policy: the teacher's policy (eval mode, no gradients are taken through it).
    :param normalizer: its ``VecNormalize`` statistics, or ``None`` if it was trained on raw observations.
    :param name: label used in logs (usually the task name).
    """

    policy: ActorCriticPolicy
    normalizer: VecNormalize | None = None
    name: str = "teacher"
    _device_normalizer: Any = field(default=None, repr=False, compare=False)

    @classmethod
    def load(
        cls,
        model_path: str | Path,
        normalizer_path: str | Path | None = None,
        name: str | None = None,
        observation_space: spaces.Space | None = None,
        device: str | th.device = "cpu",
    ) -> Teacher:
        """Load a teacher saved with ``model.save`` (+ ``VecNormalize.save``).

        :param model_path: the ``.zip`` of a PPO model.
        :param normalizer_path: its VecNormalize ``.pkl`` (``None``: raw observations).
        :param name: label (default: the file's parent folder name).
        :param observation_space: if given, the teacher's space must equal it
            (:class:`SpaceMismatchError` otherwise).
        :param device: torch device of the teacher.
        """
        model_path = Path(model_path)
        if not model_path.is_file():
            raise FileNotFoundError(f"teacher checkpoint {model_path} does not exist")
        policy = PPO.load(model_path, device=device).policy
        policy.set_training_mode(False)
        if observation_space is not None:
            check_spaces(f"teacher {model_path}", policy.observation_space, observation_space)
        normalizer = load_normalizer(normalizer_path) if normalizer_path is not None else None
        if normalizer is not None and observation_space is not None:
            check_spaces(f"normalisation statistics {normalizer_path}", normalizer.observation_space, observation_space)
        return cls(policy, normalizer, name or model_path.parent.name)

    def normalize(self, raw_obs: ObsDict) -> ObsDict:
        return raw_obs if self.normalizer is None else self.normalizer.normalize_obs(raw_obs)

    def normalize_tensors(self, raw_obs: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """:meth:`normalize` on device tensors (``VecNormalize``'s arithmetic in torch, no host copy)."""
        if self.normalizer is None:
            return dict(raw_obs)
        device = next(iter(raw_obs.values())).device
        if self._device_normalizer is None or self._device_normalizer.device != device:
            self._device_normalizer = DeviceNormalizer(self.normalizer, device)
        return self._device_normalizer.normalize_obs(raw_obs)

    @th.no_grad()
    def action_distribution(self, raw_obs: ObsDict | Mapping[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """Mean and standard deviation (B, A) of the teacher's Gaussian on raw observations (numpy
        arrays, or tensors on the teacher's device: then nothing leaves the device)."""
        if all(isinstance(v, th.Tensor) for v in raw_obs.values()):
            obs = self.normalize_tensors(raw_obs)  # type: ignore[arg-type]
        else:
            obs, _ = self.policy.obs_to_tensor(self.normalize(raw_obs))  # type: ignore[arg-type]
        normal = self.policy.get_distribution(obs).distribution
        return normal.mean, normal.stddev.expand_as(normal.mean)

    @th.no_grad()
    def value(self, raw_obs: ObsDict | Mapping[str, th.Tensor]) -> th.Tensor:
        """The teacher critic's value (B,) of raw observations (numpy, or tensors on its device)."""
        if all(isinstance(v, th.Tensor) for v in raw_obs.values()):
            obs = self.normalize_tensors(raw_obs)  # type: ignore[arg-type]
        else:
            obs, _ = self.policy.obs_to_tensor(self.normalize(raw_obs))  # type: ignore[arg-type]
        return self.policy.predict_values(obs).flatten()

    def act(self, raw_obs: ObsDict) -> np.ndarray:
        """Deterministic (mean) actions, clipped to the action space."""
        mean, _ = self.action_distribution(raw_obs)
        space = self.policy.action_space
        return np.clip(mean.cpu().numpy(), space.low, space.high)
