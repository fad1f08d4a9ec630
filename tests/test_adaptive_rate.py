"""A learning rate that targets a KL per update: arms of different parameterisations compared at equal effect."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO

from sb3_divmorph.algos.adaptive_rate import AdaptiveLearningRate, ScaledSchedule


def _ppo(rate: float) -> PPO:
    env = gym.make("Pendulum-v1")
    return PPO("MlpPolicy", env, learning_rate=rate, n_steps=128, batch_size=64, n_epochs=4, seed=0, device="cpu")


@pytest.mark.parametrize(("rate", "direction"), [(1e-7, "up"), (3e-1, "down")])
def test_the_rate_moves_towards_updates_of_the_desired_kl(rate, direction):
    """A rate far too small for a KL of 0.01 is raised update after update, one far too large lowered,
    and the optimiser runs at the schedule's rate times the multiplier (break: skip the adaptation ->
    the multiplier stays 1)."""
    model = _ppo(rate)
    adapt = AdaptiveLearningRate(desired_kl=0.01)
    model.learn(128 * 6, callback=adapt)
    multipliers = [m for _, _, m in adapt.history]
    assert len(multipliers) == 5
    if direction == "up":
        assert multipliers == sorted(multipliers) and multipliers[-1] == pytest.approx(1.5**5)
    else:
        assert multipliers == sorted(multipliers, reverse=True) and multipliers[-1] == pytest.approx(1.5**-5)
    assert model.policy.optimizer.param_groups[0]["lr"] == pytest.approx(rate * multipliers[-1], rel=1e-6)  # the last update's


def test_a_saved_run_keeps_its_multiplier(tmp_path):
    model = _ppo(1e-7)
    model.learn(128 * 4, callback=AdaptiveLearningRate(desired_kl=0.01))
    scale = model.lr_schedule.scale
    assert scale > 1
    model.save(tmp_path / "model.zip")
    loaded = PPO.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"), device="cpu")
    assert loaded.learning_rate_multiplier == scale
    again = AdaptiveLearningRate(desired_kl=0.01)
    loaded.learn(128 * 2, callback=again, reset_num_timesteps=False)
    assert isinstance(loaded.lr_schedule, ScaledSchedule) and loaded.lr_schedule(1.0) >= 1e-7 * scale
    assert again.history and again.history[0][2] == pytest.approx(scale * 1.5)  # went on from the saved multiplier
    with pytest.raises(ValueError, match="desired_kl must be > 0"):
        AdaptiveLearningRate(desired_kl=0)
    assert np.isfinite(loaded.lr_schedule(0.5))
