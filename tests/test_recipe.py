"""MetaMorph's training recipe: cosine schedule with warm-up, balanced robot sampler, zoo entries."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

import unimal_envs  # noqa: F401
from sb3_divmorph.algos.recipe import BalancedRobotSampler, CosineWarmupSchedule, balanced_probabilities
from divmorph.pipeline.config import BALANCED_SAMPLER, ConfigError, load_zoo_entry


def test_cosine_schedule_warms_up_then_decays_to_zero():
    lr = CosineWarmupSchedule(3e-4, warmup_fraction=5 / 1220, warmup_start=0.1)
    assert lr(1.0) == pytest.approx(3e-5)  # starts at 0.1x
    assert lr(1.0 - 2.5 / 1220) == pytest.approx(3e-4 * 0.55)  # half-way through the warm-up
    assert lr(1.0 - 5 / 1220) == pytest.approx(3e-4)  # the peak
    assert lr(0.5) == pytest.approx(3e-4 * 0.5, rel=1e-2)  # cosine: half the rate half-way
    assert lr(0.0) == pytest.approx(0.0, abs=1e-12)
    values = [lr(1 - f) for f in np.linspace(5 / 1220, 1, 50)]
    assert all(a >= b for a, b in zip(values, values[1:]))
    with pytest.raises(ValueError):
        CosineWarmupSchedule(3e-4, warmup_fraction=1.0)


def test_balanced_probabilities_favour_robots_with_short_episodes():
    """A synthetic log: robot 'a' falls after 50 steps, 'b' after 200, 'c' runs the full 1000."""
    sampler = BalancedRobotSampler(alpha=0.1)
    rng = np.random.default_rng(0)
    for _ in range(200):
        robot = ["a", "b", "c"][rng.integers(3)]
        length = {"a": 50, "b": 200, "c": 1000}[robot]
        sampler.record_infos([{"morphology": robot, "episode": {"l": length, "r": 0.0}}, {"morphology": robot}])
    p = sampler.probabilities_for(["a", "b", "c", "unseen"])
    # p ∝ 1000 / EMA(length): 1/50 : 1/200 : 1/1000; an unseen robot gets the mean length.
    expected = np.array([1 / 50, 1 / 200, 1 / 1000, 1 / np.mean([50, 200, 1000])])
    np.testing.assert_allclose(p, expected / expected.sum(), rtol=1e-6)
    assert p[0] > p[1] > p[2] and p.sum() == pytest.approx(1.0)
    # The EMA follows a robot that gets better (longer episodes) and its probability drops.
    for _ in range(60):
        sampler.record("a", 1000)
    assert sampler.probabilities_for(["a", "b", "c"])[0] < p[0]
    assert np.allclose(balanced_probabilities([None, None]), 0.5)


def test_sampler_sends_probabilities_to_every_worker_after_the_warm_up(train_files):
    """In a real (tiny) PPO run: episodes are logged per robot, nothing changes during the warm-up,
    then every worker draws with the balanced probabilities."""
    from stable_baselines3 import PPO

    venv = make_vec_env("Unimal-FT-v0", n_envs=2, env_kwargs=dict(morphologies=train_files[:3], max_episode_steps=5))
    sampler = BalancedRobotSampler(warmup_iterations=2)
    seen = []

    class Spy(BalancedRobotSampler):  # records what the workers hold after each rollout
        def _on_rollout_end(self) -> None:
            seen.append(venv.get_attr("_morphology_probabilities"))

    model = PPO("MultiInputPolicy", venv, n_steps=20, batch_size=40, n_epochs=1, seed=0, device="cpu")
    model.learn(120, callback=[sampler, Spy()])  # 3 rollouts of 2 x 20 steps
    names = venv.get_attr("morphology_names")[0]
    assert sampler.iterations == 3 and set(sampler.ema) <= set(names) and len(sampler.ema) >= 2
    assert seen[0] == [None, None]  # warm-up: uniform draws
    for p in seen[-1]:
        np.testing.assert_allclose(p, sampler.probabilities_for(names))
    # Robots with shorter episodes get more probability.
    lengths = [sampler.ema.get(n, np.mean(list(sampler.ema.values()))) for n in names]
    assert np.argmax(seen[-1][0]) == int(np.argmin(lengths))


def test_env_rejects_bad_probabilities(train_files):
    env = gym.make("Unimal-FT-v0", morphologies=train_files[:2]).unwrapped
    for bad in ([1.0], [-1.0, 2.0], [np.nan, 1.0], [0.0, 0.0]):
        with pytest.raises(ValueError, match="morphology probabilities"):
            env.set_morphology_probabilities(bad)
    env.set_morphology_probabilities([0.0, 1.0])
    assert {env.reset()[1]["morphology"] for _ in range(10)} == {env.morphology_names[1]}


def test_metamorph_zoo_entries_load_with_the_recipe(train_files):
    entry = load_zoo_entry("zoo_configs/ppo.yml", "Unimal-FT-v0-metamorph")
    assert isinstance(entry.ppo_kwargs["learning_rate"], CosineWarmupSchedule)
    assert entry.ppo_kwargs["target_kl"] * 1.5 == pytest.approx(0.2, abs=1e-3)
    assert entry.policy_kwargs["optimizer_kwargs"] == {"eps": 1e-5}
    assert entry.normalize["clip_obs"] == 10.0 and entry.normalize["clip_reward"] == 10.0
    assert entry.callbacks == [(BALANCED_SAMPLER, {})]
    # The policy hands the optimizer its eps (MetaMorph's Adam eps 1e-5).
    from stable_baselines3 import PPO

    import sb3_divmorph  # noqa: F401  (policy aliases)

    model = PPO(
        entry.policy,
        make_vec_env("Unimal-FT-v0", n_envs=1, env_kwargs=dict(morphologies=train_files[:1])),
        policy_kwargs=entry.policy_kwargs,
        n_steps=16,
        batch_size=16,
        device="cpu",
    )
    assert model.policy.optimizer.defaults["eps"] == 1e-5
    with pytest.raises(ConfigError, match="supports only callback"):
        load_zoo_entry("zoo_configs/ppo.yml", "Unimal-FT-v0", {"callback": "some.OtherCallback"})
