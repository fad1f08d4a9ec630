"""``VecNormalize`` for dict observations without the deep copy of every observation.

SB3's ``VecNormalize.normalize_obs`` deep-copies the observation dict before it writes the normalised keys
(``copy.deepcopy``: a Python walk over every key and array, at every env step), a sizeable share of a cheap
env's step (``benchmarks/cpu_training.py`` measures it). The arrays a ``DummyVecEnv`` returns are already its
own copies; here each key's array is copied once with ``ndarray.copy`` and the normalised keys are written as
SB3 writes them, so the result is the same arrays, values and dtypes, and the returned dict shares nothing with
the original observation (``get_original_obs``) that a caller could change.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecNormalize


class LeanVecNormalize(VecNormalize):
    """SB3's :class:`~stable_baselines3.common.vec_env.VecNormalize` (same arguments, statistics, saving and
    loading), whose :meth:`normalize_obs` copies a dict observation key by key instead of deep-copying it."""

    @classmethod
    def load(cls, load_path: str, venv: VecEnv) -> LeanVecNormalize:
        """Load saved statistics (also those a plain ``VecNormalize`` saved, which become this class: it adds
        no state of its own) and wrap ``venv``."""
        normalizer = super().load(load_path, venv)
        if type(normalizer) is VecNormalize:
            normalizer.__class__ = cls
        assert isinstance(normalizer, cls)
        return normalizer

    def normalize_obs(self, obs):
        if not isinstance(obs, dict):
            return super().normalize_obs(obs)
        normalized = {key: np.array(value, copy=True) for key, value in obs.items()}
        if self.norm_obs:
            for key in self.norm_obs_keys:
                normalized[key] = self._normalize_obs(obs[key], self.obs_rms[key]).astype(np.float32)
        return normalized
