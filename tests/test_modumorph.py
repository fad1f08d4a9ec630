"""ModuMorphPolicy: fixed attention, hypernetwork init, masking, batching, save/load, PPO, folded actor."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO

from sb3_divmorph import MetaMorphPolicy, ModuMorphPolicy
from sb3_divmorph.deploy.compact import actor_inputs, export_torchscript
from sb3_divmorph.deploy.modumorph_actor import ModuMorphActor
from sb3_divmorph.policies.modumorph import DECODER_INIT, EMBEDDING_INIT, HyperLinear
from sb3_divmorph.testing import random_observations
import unimal_envs
from unimal_envs import contract

th.set_num_threads(1)

SPACE = contract.observation_space()
ACTION_SPACE = contract.action_space()
TINY = dict(
    d_model=16,
    n_layers=2,
    n_heads=2,
    ff_dim=32,
    hypernet_dim=8,
    net_arch=dict(pi=[16], vf=[16]),
    exteroception=dict(hfield=[8], goal=[4], object=[4]),
)
VARIANTS = {
    "modumorph": {},
    "no-fixed-attention": dict(fixed_attention=False),
    "no-hypernetwork": dict(hypernetwork=False),
    "shared": dict(share_features_extractor=True),
}


def make_policy(seed: int = 0, **overrides) -> ModuMorphPolicy:
    th.manual_seed(seed)
    return ModuMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, **{**TINY, **overrides})


def batch(policy, size: int = 20, seed: int = 0) -> dict[str, th.Tensor]:
    return policy.obs_to_tensor(random_observations(SPACE, size, seed=seed, n_morphologies=4, n_tasks=2))[0]


def perturb_weights(policy: ModuMorphPolicy, seed: int = 1) -> None:
    """Move every parameter off its init (generators start at zero, which would hide the context)."""
    g = th.Generator().manual_seed(seed)
    with th.no_grad():
        for p in policy.parameters():
            p.add_(th.randn(p.shape, generator=g) * 0.05)


def evaluate(policy, obs, actions, train):
    policy.set_training_mode(train)
    with th.set_grad_enabled(train):
        return policy.evaluate_actions(obs, actions)


def test_alias_presets_and_sizes():
    assert PPO.policy_aliases["ModuMorphPolicy"] is ModuMorphPolicy
    paper = ModuMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, preset="paper", exteroception={}, net_arch=dict(pi=[], vf=[]))
    extractor = paper.pi_features_extractor
    assert len(extractor.layers) == 5 and extractor.d_model == 128 and extractor.layers[0].ff_in.out_features == 1024
    assert not any("position" in name for name, _ in paper.named_parameters())
    counts = paper.parameter_counts()
    actor = sum(v for k, v in counts.items() if k.startswith("actor/"))
    # the authors' FT actor (decoder Linear(128 -> 2), generated) has ~2.62M parameters; MetaMorph ~1.66M
    assert 2.55e6 < actor < 2.7e6, actor
    meta = MetaMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, preset="paper", exteroception={}, net_arch=dict(pi=[], vf=[]))
    assert actor / sum(v for k, v in meta.parameter_counts().items() if k.startswith("actor/")) > 1.5
    with pytest.raises(ValueError, match="embedding dropout"):
        ModuMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, embedding_dropout=0.1)


def test_fixed_attention_depends_on_the_morphology_only():
    policy = make_policy()
    perturb_weights(policy)
    obs = batch(policy)
    real = obs["obs_padding_mask"] < 0.5
    before = policy.attention_weights(obs)
    other_state = {k: v.clone() for k, v in obs.items()}
    other_state["proprioceptive"][real] += th.randn(int(real.sum()), contract.PROPRIO_DIM) * 3
    other_state["hfield"] += 1.0
    after = policy.attention_weights(other_state)
    assert len(before) == 2
    assert all(th.equal(a, b) for a, b in zip(before, after))
    # the proprioception did change what the actor does
    assert not th.allclose(policy.get_distribution(obs).mode(), policy.get_distribution(other_state).mode())
    other_robot = {k: v.clone() for k, v in obs.items()}
    other_robot["context"][real] += th.randn(int(real.sum()), other_robot["context"].shape[-1])
    changed = policy.attention_weights(other_robot)
    assert all(not th.allclose(a, b, atol=1e-4) for a, b in zip(before, changed))
    # control: MetaMorph-style attention (ablation) does move with the state
    ablated = make_policy(fixed_attention=False)
    perturb_weights(ablated)
    assert not th.allclose(ablated.attention_weights(obs)[0], ablated.attention_weights(other_state)[0], atol=1e-4)


def test_hypernetwork_init_gives_every_limb_the_generators_bias():
    policy = make_policy()
    obs = batch(policy)
    extractor = policy.pi_features_extractor
    hyper = extractor.hypernet_encoder(obs["context"])  # (B, L, h): differs across robots and limbs
    assert not th.allclose(hyper, hyper[:1].expand_as(hyper))
    generators = [(extractor.embedding, EMBEDDING_INIT)] + [(layer, DECODER_INIT) for layer in policy.mlp_extractor.policy_net.layers]
    generators += [(layer, DECODER_INIT) for layer in policy.mlp_extractor.value_net.layers]
    for layer, init_range in generators:
        assert isinstance(layer, HyperLinear)
        weight, bias = layer.generate(hyper)
        expected_w = layer.weight_generator.bias.view(layer.in_dim, layer.out_dim)
        assert th.equal(weight, expected_w.expand_as(weight)) and th.equal(bias, layer.bias_generator.bias.expand_as(bias))
        for generated in (expected_w.detach(), layer.bias_generator.bias.detach()):
            assert generated.abs().max() <= init_range
            if generated.numel() >= 64:  # U(-r, r): spread over the range, centred on zero
                assert generated.abs().max() > 0.8 * init_range and abs(float(generated.mean())) < 0.2 * init_range
        assert th.count_nonzero(layer.weight_generator.weight) == 0
    # once trained (weights moved), generated weights depend on the limb's context
    perturb_weights(policy)
    weight, _ = extractor.embedding.generate(extractor.hypernet_encoder(obs["context"]))
    assert not th.allclose(weight[0, 0], weight[0, 1])


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_padded_tokens_and_slots_change_nothing(variant):
    policy = make_policy(**VARIANTS[variant])
    perturb_weights(policy)
    obs = batch(policy)
    padded_tok = obs["obs_padding_mask"] > 0.5
    padded_slot = obs["act_padding_mask"] > 0.5
    actions = th.rand(20, 24) * 2 - 1
    for train in (True, False):
        values, log_prob, entropy = evaluate(policy, obs, actions, train)
        mode = policy.get_distribution(obs).mode()
        changed = {k: v.clone() for k, v in obs.items()}
        changed["proprioceptive"][padded_tok] = float("nan")
        changed["context"][padded_tok] = th.randn(int(padded_tok.sum()), changed["context"].shape[-1]) * 10
        other_actions = actions.clone()
        other_actions[padded_slot] = th.randn(int(padded_slot.sum())) * 10
        values2, log_prob2, entropy2 = evaluate(policy, changed, other_actions, train)
        assert th.allclose(values, values2, atol=1e-5) and th.allclose(log_prob, log_prob2, atol=1e-5)
        assert th.allclose(entropy, entropy2)
        mode2 = policy.get_distribution(changed).mode()
        assert th.allclose(mode, mode2, atol=1e-6) and th.all(mode2[padded_slot] == 0)
    # control: a real token changes value and log-prob
    changed = {k: v.clone() for k, v in obs.items()}
    changed["proprioceptive"][~padded_tok] += 1.0
    values3, log_prob3, _ = evaluate(policy, changed, actions, False)
    assert not th.allclose(values, values3, atol=1e-4) and not th.allclose(log_prob, log_prob3, atol=1e-4)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_mixed_batch_equals_per_sample_evaluation(variant):
    policy = make_policy(**VARIANTS[variant])
    perturb_weights(policy)
    obs = batch(policy, size=12)
    actions = th.rand(12, 24) * 2 - 1
    values, log_prob, entropy = evaluate(policy, obs, actions, False)
    for i in range(12):
        v, lp, ent = evaluate(policy, {k: x[i : i + 1] for k, x in obs.items()}, actions[i : i + 1], False)
        assert th.allclose(v, values[i : i + 1], atol=1e-5) and th.allclose(lp, log_prob[i : i + 1], atol=1e-4)
        assert th.allclose(ent, entropy[i : i + 1])


def test_save_load_roundtrip(tmp_path):
    from test_policies import StandInEnv

    model = PPO(
        "ModuMorphPolicy",
        StandInEnv(),
        n_steps=32,
        batch_size=16,
        n_epochs=1,
        seed=0,
        policy_kwargs=dict(TINY, fixed_attention=True, hypernetwork=True),
    )
    model.learn(64)
    model.save(tmp_path / "model")
    loaded = PPO.load(tmp_path / "model", device="cpu")
    assert type(loaded.policy) is ModuMorphPolicy and loaded.policy.config["hypernet_dim"] == 8
    original, restored = model.policy.state_dict(), loaded.policy.state_dict()
    assert original.keys() == restored.keys() and all(th.equal(original[k], restored[k]) for k in original)
    obs = random_observations(SPACE, 8, seed=5)
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    model.policy.save(tmp_path / "policy.pth")
    assert np.array_equal(
        model.predict(obs, deterministic=True)[0], ModuMorphPolicy.load(tmp_path / "policy.pth").predict(obs, deterministic=True)[0]
    )


def test_ppo_improves_return_on_flat_terrain():
    from test_policies import FT_MARGIN, _ft_improvement

    gains = [_ft_improvement("ModuMorphPolicy", seed) for seed in (0, 1)]
    assert min(gains) > FT_MARGIN, gains


@pytest.mark.parametrize("variant", ["modumorph", "no-hypernetwork", "no-fixed-attention"])
def test_folded_actor_equals_the_policy(variant, tmp_path, train_files):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from unimal_envs.tasks import TASKS

    task = "VT"
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=train_files[:1], max_episode_steps=30)]),
        norm_obs_keys=["proprioceptive"],
    )
    model = PPO("ModuMorphPolicy", venv, n_steps=32, batch_size=32, n_epochs=1, seed=0, policy_kwargs=dict(TINY, **VARIANTS[variant]))
    model.learn(32)
    perturb_weights(model.policy)
    venv.training = False
    venv.reset()
    raw = [venv.get_original_obs()]
    for _ in range(5):
        venv.step(np.random.uniform(-1, 1, (1, 24)).astype(np.float32))
        raw.append(venv.get_original_obs())
    obs = {k: np.concatenate([r[k] for r in raw]) for k in raw[0]}
    actor = ModuMorphActor.from_policy(model.policy, {k: v[0] for k, v in obs.items()}, TASKS[task].observation_keys, venv)
    with th.no_grad():
        reference = model.policy.get_distribution(model.policy.obs_to_tensor(venv.normalize_obs(obs))[0]).distribution.mean
        got = actor(*actor_inputs(obs, batch=True))
    assert (reference - got).abs().max() <= 1e-5
    assert not any(n.startswith(("context_encoder", "hypernet")) for n, _ in actor.named_parameters())
    path = export_torchscript(actor, {k: v[0] for k, v in obs.items()}, tmp_path / "actor.pt", {"task": task})
    assert (th.jit.load(str(path))(*actor_inputs(obs, batch=True)) - reference).abs().max() <= 1e-5
