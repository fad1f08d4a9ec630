"""Transfer with fixed gates is exact: unselected tailors never move, the configured learning-rate
ratio is the one applied."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_divmorph  # noqa: F401
import unimal_envs  # noqa: F401
from sb3_divmorph.finetune import UnitSelection, actor_modules, prepare_transfer
from sb3_divmorph.layers import FactorizedLinear
from unimal_envs.morphology.loader import morphology_files

TINY_DIVMORPH = dict(
    d_model=16, n_layers=1, ff_dim=32, exteroception=dict(hfield=[8], goal=[4], object=[4]),
    n_morph_tailors=6, n_task_tailors=6, top_k_morph=2, top_k_task=2,
)
ROBOTS = morphology_files("train")[:2]


def distilled_like_student(seed: int = 0, **ppo_kwargs) -> tuple[PPO, VecNormalize]:
    """A tiny DivMorph PPO on Escape whose square factors have been rotated (skew != 0), as after
    distillation."""
    th.manual_seed(seed)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("Unimal-Escape-v0", morphologies=ROBOTS, max_episode_steps=50)]),
                        norm_obs_keys=["proprioceptive"])
    kwargs = dict(n_steps=64, batch_size=16, n_epochs=5, learning_rate=3e-3, seed=seed)
    model = PPO("DivMorphPolicy", venv, policy_kwargs=TINY_DIVMORPH, **{**kwargs, **ppo_kwargs})
    with th.no_grad():
        for layer in model.policy.modules():
            if isinstance(layer, FactorizedLinear) and layer.orthogonal:
                layer.square_skew.normal_(0, 0.2)
    return model, venv


def diverted_actor_layers(policy) -> list[FactorizedLinear]:
    return [m for module in actor_modules(policy) for m in module.modules() if isinstance(m, FactorizedLinear) and m.n_tailors]


def snapshot(layer: FactorizedLinear) -> dict[str, th.Tensor]:
    with th.no_grad():
        return {"square": layer.square_factor().clone(), "s": layer.singular_values.clone(), "tall": layer.tall.clone()}


def test_unselected_tailors_stay_exactly_frozen_over_a_ppo_run():
    model, venv = distilled_like_student()
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    assert 0 < selection.tailors.sum() < len(selection.tailors)
    with th.no_grad():
        mean_before = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0]).distribution.mean.clone()
    prepare_transfer(model.policy, selection, learngene_scale=0.1)
    with th.no_grad():  # re-basing the square factors changes nothing the policy computes
        mean_after = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0]).distribution.mean
    assert th.allclose(mean_before, mean_after, atol=1e-6)
    layers = diverted_actor_layers(model.policy)
    before = [snapshot(layer) for layer in layers]
    model.learn(128)  # 2 rollouts x 5 epochs x 4 minibatches = 40 optimiser updates
    assert model.policy.optimizer.state, "the run made no optimiser step"

    for layer, old in zip(layers, before):
        new = snapshot(layer)
        tailor = th.arange(layer.rank) >= layer.n_learngenes
        frozen = th.zeros(layer.rank, dtype=th.bool)
        frozen[tailor] = th.as_tensor(~selection.tailors)
        for name in ("square", "s", "tall"):
            delta = (new[name] - old[name]).abs()
            delta = delta[..., frozen] if delta.dim() == 2 else delta[frozen]
            assert delta.max().item() == 0.0, f"{layer}: unselected {name} moved by {delta.max().item():.2e}"
        moved_selected = (new["square"] - old["square"]).abs()[:, tailor & ~frozen]
        assert moved_selected.max() > 0, "selected tailors' square-factor columns never moved"
        assert (new["s"] - old["s"]).abs()[: layer.n_learngenes].max() > 0


@pytest.mark.parametrize("ratio", [0.1, 0.3])
def test_the_configured_learning_rate_ratio_is_the_one_applied_with_tiny_gradients(ratio):
    """A distilled student's tailor gradients (~1e-6) are below SB3's Adam eps (1e-5); transfer
    must still apply learngene / selected-tailor updates at the configured ratio."""
    model, venv = distilled_like_student(seed=1)
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    rates = prepare_transfer(model.policy, selection, learngene_scale=ratio)
    batch = {k: np.repeat(v, 32, axis=0) for k, v in obs.items()}
    obs_t, _ = model.policy.obs_to_tensor(batch)
    actions = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (32, 24)).astype(np.float32))
    for _ in range(20):
        loss = -model.policy.get_distribution(obs_t).log_prob(actions).mean() * 1e-5  # gradients ~1e-6 and below
        model.policy.optimizer.zero_grad()
        loss.backward()
        model.policy.optimizer.step()
    measured = rates.measured_ratio()
    assert 0.7 * ratio <= measured <= 1.4 * ratio, f"configured {ratio}, applied {measured:.3f}"


def test_sb3_default_adam_eps_would_break_the_ratio():
    """The check above can fail: with SB3's eps the applied ratio drifts from the configured one."""
    model, venv = distilled_like_student(seed=1)
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    rates = prepare_transfer(model.policy, selection, learngene_scale=0.1, adam_eps=None)
    assert model.policy.optimizer.param_groups[0]["eps"] == 1e-5
    batch = {k: np.repeat(v, 32, axis=0) for k, v in obs.items()}
    obs_t, _ = model.policy.obs_to_tensor(batch)
    actions = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (32, 24)).astype(np.float32))
    for _ in range(20):
        loss = -model.policy.get_distribution(obs_t).log_prob(actions).mean() * 1e-5
        model.policy.optimizer.zero_grad()
        loss.backward()
        model.policy.optimizer.step()
    assert not 0.07 <= rates.measured_ratio() <= 0.14
