"""A saved model and its observation statistics, from the model file alone.

A policy trained on normalised observations acts only through the statistics it was trained with:
:func:`load_model` loads both (SB3 keeps them apart: the ``.zip`` and rl-zoo's / the pipeline's
``vecnormalize.pkl``) and :meth:`NormalizedModel.predict` applies them::

    from sb3_divmorph import load_model

    actor = load_model("teachers/FT/model.zip")        # vecnormalize.pkl beside it is found
    action = actor.predict(obs)                         # statistics applied, deterministic

Which robots and env settings a model was trained with is its run's business (the application's
:func:`divmorph.pretrained.load_pretrained` reads run folders).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.distillation import load_normalizer

#: the statistics' file name next to a model (the pipeline's stages and rl-zoo's ``<env id>/`` folder)
NORMALIZER = "vecnormalize.pkl"
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"ppo": PPO, "a2c": A2C}


class SavedModelError(ValueError):
    """The model file is not a whole SB3 archive, or its algorithm or statistics cannot be read."""


@dataclass
class NormalizedModel:
    """An SB3 model with the frozen observation statistics it was trained with.

    :param model: the SB3 algorithm (``model.policy`` is the network).
    :param normalizer: its ``VecNormalize`` statistics (``None``: trained on raw observations).
    """

    model: BaseAlgorithm
    normalizer: VecNormalize | None = None

    def normalize(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``obs`` as the policy saw its observations in training."""
        if self.normalizer is None:
            return obs
        return cast(dict[str, np.ndarray], self.normalizer.normalize_obs(obs))  # a dict in, a dict out

    def predict(self, obs: dict[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
        """The model's action for a (single or batched) observation, its statistics applied."""
        action, _ = self.model.predict(self.normalize(obs), deterministic=deterministic)
        return action


def check_archive(model: str | Path) -> None:
    """Refuse, by name, a model file that is not a whole SB3 archive (cut off by a copy, or another file).

    :raises SavedModelError: not a readable zip, or a zip without SB3's ``data`` entry.
    """
    try:
        with zipfile.ZipFile(model) as archive:
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError) as error:
        raise SavedModelError(f"{model}: truncated or not a model archive ({error}); save or copy the model again") from None
    if "data" not in names:
        raise SavedModelError(f"{model}: truncated or not a model archive (a zip without Stable-Baselines3's 'data' entry)")


def load_model(model: str | Path, normalizer: str | Path | None = None, device: str = "cpu", algo: str = "ppo") -> NormalizedModel:
    """Load a saved model and its observation statistics.

    :param model: the ``.zip`` SB3 saved.
    :param normalizer: its ``VecNormalize`` file (default: ``vecnormalize.pkl`` beside the model, if
        there is one; otherwise the model acts on raw observations).
    :param device: where the network runs.
    :param algo: ``ppo`` or ``a2c`` (the policies are on-policy actor-critics).
    :raises SavedModelError: an unknown algorithm, or a truncated or foreign model file.
    """
    if algo not in ALGORITHMS:
        raise SavedModelError(f"unknown algorithm {algo!r}; choose from {list(ALGORITHMS)}")
    model = Path(model)
    check_archive(model)
    if normalizer is None and (model.parent / NORMALIZER).is_file():
        normalizer = model.parent / NORMALIZER
    loaded: Any = ALGORITHMS[algo].load(model, device=device)
    return NormalizedModel(loaded, load_normalizer(normalizer) if normalizer is not None else None)
