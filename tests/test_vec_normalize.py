"""``LeanVecNormalize`` normalises a dict observation exactly as SB3's ``VecNormalize`` does, without its deep copy."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import unimal_envs
from divmorph.pipeline.envs import normalizer_for
from sb3_divmorph.algos.vec_normalize import LeanVecNormalize


def unimal_venv(robots):
    return DummyVecEnv([lambda: gym.make(unimal_envs.env_id("FT"), morphologies=robots) for _ in range(2)])


def test_the_same_normalised_observations_rewards_and_statistics(train_files):
    """Both wrappers over the same envs, seeds and actions: every key's values and dtype equal at every step, and
    the statistics they learn (broken once: the lean copy skipped the normalisation of one key -> fails)."""
    robots = train_files[:2]
    plain = VecNormalize(unimal_venv(robots), norm_obs_keys=["proprioceptive", "context"])
    lean = LeanVecNormalize(unimal_venv(robots), norm_obs_keys=["proprioceptive", "context"])
    for venv in (plain, lean):
        venv.seed(3)
    obs_a, obs_b = plain.reset(), lean.reset()
    rng = np.random.default_rng(0)
    for _ in range(20):
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key], err_msg=key)
            assert obs_a[key].dtype == obs_b[key].dtype
        actions = rng.uniform(-1, 1, (2, *plain.action_space.shape))
        obs_a, reward_a, done_a, _ = plain.step(actions)
        obs_b, reward_b, done_b, _ = lean.step(actions)
        np.testing.assert_array_equal(reward_a, reward_b)
        np.testing.assert_array_equal(done_a, done_b)
    for key in ("proprioceptive", "context"):
        np.testing.assert_array_equal(plain.obs_rms[key].mean, lean.obs_rms[key].mean)


def test_the_returned_observation_shares_no_array_with_the_original(train_files):
    """A caller writing into the normalised observation leaves the original one alone (broken once: the dict
    copied without its arrays -> fails)."""
    lean = LeanVecNormalize(unimal_venv(train_files[:2]), norm_obs_keys=["proprioceptive"])
    obs = lean.reset()
    original = lean.get_original_obs()
    before = {key: value.copy() for key, value in original.items()}
    for value in obs.values():
        value[...] = 123
    for key, value in lean.get_original_obs().items():
        np.testing.assert_array_equal(value, before[key], err_msg=key)


def test_saved_plain_statistics_load_as_lean_and_the_pipeline_wraps_with_it(train_files, tmp_path):
    plain = VecNormalize(unimal_venv(train_files[:2]))
    plain.reset()
    plain.save(str(tmp_path / "vecnormalize.pkl"))
    loaded = LeanVecNormalize.load(str(tmp_path / "vecnormalize.pkl"), unimal_venv(train_files[:2]))
    assert type(loaded) is LeanVecNormalize
    np.testing.assert_array_equal(loaded.obs_rms["proprioceptive"].mean, plain.obs_rms["proprioceptive"].mean)
    assert type(normalizer_for(unimal_venv(train_files[:2]), {"norm_obs": True}, 0.99)) is LeanVecNormalize
