"""Saved ``VecNormalize`` statistics, read without an env."""

from __future__ import annotations

import pickle
from pathlib import Path

from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.distillation.space_checks import SpaceMismatchError


def load_normalizer(path: str | Path) -> VecNormalize:
    """Unpickle saved ``VecNormalize`` statistics without attaching an env (only ``normalize_obs`` is used)."""
    with open(path, "rb") as f:
        normalizer = pickle.load(f)
    if not isinstance(normalizer, VecNormalize):
        raise SpaceMismatchError(f"{path} does not hold VecNormalize statistics (found {type(normalizer).__name__})")
    normalizer.training = False
    return normalizer
