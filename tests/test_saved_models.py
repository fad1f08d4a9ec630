"""A model saved by an earlier version of the code loads and acts as it did then.

The models under ``tests/data/saved_before`` were saved by the commit ``made_by.json`` names (the one before the
fused rollout pass and the inference-mode rollouts), with their deterministic actions and values on fixed
observations (``make.py`` there says how). Today's code must load them and give the same numbers, through
today's rollout path (the fused pass) and through the separate towers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO

DATA = Path(__file__).parent / "data" / "saved_before"


@pytest.mark.parametrize("policy", ["MetaMorphPolicy", "DivMorphPolicy"])
@pytest.mark.parametrize("fuse", [True, False])
def test_a_model_saved_before_loads_and_acts_the_same(policy, fuse):
    """(broken once: the fused pass's critic weights scaled by 1.001 -> the values differ)"""
    expected = dict(np.load(DATA / "expected.npz"))
    observations = {key.split("/", 1)[1]: value for key, value in expected.items() if key.startswith("obs/")}
    model = PPO.load(DATA / f"{policy}.zip", device="cpu")
    model.policy.fuse_rollout_towers = fuse
    actions, _ = model.predict(observations, deterministic=True)
    obs_t, _ = model.policy.obs_to_tensor(observations)
    with th.no_grad():
        _, values, _ = model.policy(obs_t, deterministic=True)
    np.testing.assert_allclose(actions, expected[f"{policy}/actions"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(values.numpy(), expected[f"{policy}/values"], rtol=1e-5, atol=1e-6)
