"""Tests of MetaMorphPolicy and DivMorphPolicy.

Unit tests use synthetic observation batches (``sb3_divmorph.testing.random_observations``) or a
tiny stand-in env with the contract spaces; only the learning test runs the MuJoCo FT task.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

import sb3_divmorph
from sb3_divmorph import DivMorphPolicy, MetaMorphPolicy
from sb3_divmorph.nn.layers import FactorizedLinear
from sb3_divmorph.testing import random_observations
from unimal_envs import contract

th.set_num_threads(1)

SPACE = contract.observation_space()
ACTION_SPACE = contract.action_space()
TINY = dict(
    d_model=16,
    n_layers=1,
    n_heads=2,
    ff_dim=32,
    net_arch=dict(pi=[16], vf=[16]),
    exteroception=dict(hfield=[8], goal=[4], object=[4]),
)
TINY_DIVMORPH = dict(TINY, n_morph_tailors=3, n_task_tailors=3, top_k_morph=2, top_k_task=2, morph_embed_dim=8, gate_hidden_dim=8)
VARIANTS = {
    "metamorph": (MetaMorphPolicy, TINY),
    "metamorph-shared": (MetaMorphPolicy, dict(TINY, share_features_extractor=True)),
    "divmorph": (DivMorphPolicy, TINY_DIVMORPH),
    "divmorph-critic": (DivMorphPolicy, dict(TINY_DIVMORPH, factorize_critic=True)),
    "divmorph-shared": (DivMorphPolicy, dict(TINY_DIVMORPH, share_features_extractor=True)),
}


def make_policy(variant: str, seed: int = 0, **overrides):
    cls, kwargs = VARIANTS[variant]
    th.manual_seed(seed)
    return cls(SPACE, ACTION_SPACE, lambda _: 3e-4, **{**kwargs, **overrides})


def batch(policy, size: int = 20, seed: int = 0, **kwargs) -> dict[str, th.Tensor]:
    obs = random_observations(SPACE, size, seed=seed, **{"n_morphologies": 4, "n_tasks": 3, **kwargs})
    return policy.obs_to_tensor(obs)[0]


def evaluate(policy, obs, actions, train: bool):
    policy.set_training_mode(train)
    with th.set_grad_enabled(train):  # SB3 collects rollouts in eval mode under no_grad
        return policy.evaluate_actions(obs, actions)


def _copy(obs: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    return {key: value.clone() for key, value in obs.items()}


# -- registration and construction ---------------------------------------------------------------
def test_policies_are_ppo_aliases():
    assert PPO.policy_aliases["MetaMorphPolicy"] is MetaMorphPolicy
    assert PPO.policy_aliases["DivMorphPolicy"] is DivMorphPolicy
    assert sb3_divmorph.DivMorphPolicy is DivMorphPolicy


def test_presets_and_overrides():
    paper = MetaMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, preset="paper")
    encoder = paper.pi_features_extractor.encoder
    assert paper.pi_features_extractor is not paper.vf_features_extractor  # MetaMorph: separate nets
    assert len(encoder.layers) == 5 and encoder.layers[0].attention.n_heads == 2
    assert encoder.layers[0].ff_in.weight.shape == (1024, 128)
    assert isinstance(paper.log_std, th.Tensor) and not isinstance(paper.log_std, th.nn.Parameter)
    assert th.allclose(paper.log_std.exp(), th.full((24,), 0.9))
    small = MetaMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, preset="paper", n_layers=1, d_model=32)
    assert len(small.pi_features_extractor.encoder.layers) == 1 and small.features_dim == 32 + 64 + 32 + 32
    with pytest.raises(ValueError):
        MetaMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, preset="huge")
    with pytest.raises(ValueError):
        MetaMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, ortho_init=True)


def test_the_metamorph_preset_is_metamorphs_reference_network(tmp_path):
    """``preset="metamorph"``: the paper sizes, no context input (the actions ignore it), a linear
    per-token decoder, and embedding dropout 0.1 that MetaMorph's code applies when it samples
    rollout actions (its model never leaves train mode) but that ``predict`` never applies."""
    policy = make_policy("metamorph", preset="metamorph", net_arch=None, d_model=None, n_layers=None, ff_dim=None)
    assert policy.config["d_model"] == 128 and len(policy.pi_features_extractor.encoder.layers) == 5
    assert policy.mlp_extractor.latent_dim_pi == policy.features_dim  # no hidden decoder layer
    policy.set_training_mode(False)
    obs = batch(policy)
    moved = {**obs, "context": obs["context"] + 1.0}
    with th.no_grad():
        first, again = policy.get_distribution(obs).distribution.mean, policy.get_distribution(moved).distribution.mean
        rollout = [policy(obs, deterministic=True)[0] for _ in range(2)]
    assert th.equal(first, again)  # context is not an input
    assert not th.equal(rollout[0], rollout[1])  # dropout while sampling rollouts, in eval mode
    numpy_obs = {k: v.numpy() for k, v in obs.items()}
    assert np.array_equal(policy.predict(numpy_obs, deterministic=True)[0], policy.predict(numpy_obs, deterministic=True)[0])
    # the project's default keeps the context, the decoder layer, and no dropout anywhere
    default = make_policy("metamorph")
    default.set_training_mode(False)
    with th.no_grad():
        assert th.equal(default(batch(default), deterministic=True)[0], default(batch(default), deterministic=True)[0])
        assert not th.equal(default.get_distribution(obs).distribution.mean, default.get_distribution(moved).distribution.mean)
    # the settings travel with a saved policy
    policy.save(tmp_path / "policy.pth")
    loaded = MetaMorphPolicy.load(tmp_path / "policy.pth")
    assert {k: loaded.config[k] for k in ("use_context", "embedding_dropout", "embedding_dropout_in_rollouts")} == {
        "use_context": False,
        "embedding_dropout": 0.1,
        "embedding_dropout_in_rollouts": True,
    }


def test_divmorph_factorizes_transformer_and_decoder():
    policy = make_policy("divmorph")
    layer = policy.pi_features_extractor.encoder.layers[0]
    projections = [layer.attention.q, layer.attention.k, layer.attention.v, layer.attention.o, layer.ff_in, layer.ff_out]
    assert all(isinstance(p, FactorizedLinear) and p.n_tailors == 6 and p.n_learngenes == 10 for p in projections)
    decoder = policy.mlp_extractor.policy_net.layers[0]
    assert isinstance(decoder, FactorizedLinear) and decoder.n_tailors == 6
    assert isinstance(policy.action_net, FactorizedLinear) and policy.action_net.n_tailors == 0  # rank 2
    # default critic: MetaMorph's (dense); factorize_critic=True diverts it too
    assert not any(isinstance(m, FactorizedLinear) for m in policy.vf_features_extractor.modules())
    critic = make_policy("divmorph-critic")
    assert isinstance(critic.vf_features_extractor.encoder.layers[0].ff_in, FactorizedLinear)


def test_divmorph_ablation_switches():
    no_transformer = make_policy("divmorph", divert_transformer=False)
    assert no_transformer.pi_features_extractor.encoder.layers[0].ff_in.n_tailors == 0
    assert no_transformer.mlp_extractor.policy_net.layers[0].n_tailors == 6
    no_decoder = make_policy("divmorph", divert_decoder=False)
    assert no_decoder.pi_features_extractor.encoder.layers[0].ff_in.n_tailors == 6
    assert no_decoder.mlp_extractor.policy_net.layers[0].n_tailors == 0
    free = make_policy("divmorph", orthogonal=False)
    assert not any("square_skew" in name for name, _ in free.named_parameters())
    # with both diversions off nothing is gated: the task embedding has no effect
    ungated = make_policy("divmorph", divert_transformer=False, divert_decoder=False)
    obs = batch(ungated)
    other_task = _copy(obs)
    other_task["task_embedding"] = th.flip(obs["task_embedding"], dims=[0])
    assert th.allclose(ungated.get_distribution(obs).mode(), ungated.get_distribution(other_task).mode())
    gated = make_policy("divmorph")
    assert not th.allclose(gated.get_distribution(obs).mode(), gated.get_distribution(other_task).mode())


# -- masking -------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("train", [True, False])
def test_padded_action_slots_change_nothing(variant, train):
    policy = make_policy(variant)
    obs = batch(policy)
    padded = obs["act_padding_mask"] > 0.5
    actions = th.rand(20, 24) * 2 - 1
    values, log_prob, entropy = evaluate(policy, obs, actions, train)
    changed = actions.clone()
    changed[padded] = th.randn(int(padded.sum())) * 10
    values2, log_prob2, entropy2 = evaluate(policy, obs, changed, train)
    assert th.allclose(log_prob, log_prob2) and th.allclose(entropy, entropy2) and th.allclose(values, values2)
    # entropy counts real slots only: n_real x H(N(0, 0.9))
    n_real = (~padded).sum(1).float()
    assert th.allclose(entropy, n_real * (0.5 * math.log(2 * math.pi * math.e) + math.log(0.9)), atol=1e-5)
    # control: a real slot does change the log-prob
    changed[~padded] += 0.5
    assert not th.allclose(log_prob, evaluate(policy, obs, changed, train)[1])


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("train", [True, False])
def test_padded_tokens_change_nothing(variant, train):
    policy = make_policy(variant)
    obs = batch(policy)
    padded = obs["obs_padding_mask"] > 0.5
    actions = th.rand(20, 24) * 2 - 1
    values, log_prob, _ = evaluate(policy, obs, actions, train)
    changed = _copy(obs)
    for key in ("proprioceptive", "context"):  # e.g. VecNormalize makes padded rows non-zero
        changed[key][padded] = th.randn(int(padded.sum()), changed[key].shape[-1]) * 10
    values2, log_prob2, _ = evaluate(policy, changed, actions, train)
    assert th.allclose(values, values2, atol=1e-5) and th.allclose(log_prob, log_prob2, atol=1e-5)
    # control: a real token does change value and log-prob
    changed["proprioceptive"][~padded] += th.randn(int((~padded).sum()), contract.PROPRIO_DIM)
    values3, log_prob3, _ = evaluate(policy, changed, actions, train)
    assert not th.allclose(values, values3, atol=1e-4) and not th.allclose(log_prob, log_prob3, atol=1e-4)


@pytest.mark.parametrize("variant", ["metamorph", "divmorph"])
def test_non_finite_padded_rows_are_harmless(variant):
    policy = make_policy(variant)
    obs = batch(policy)
    padded = obs["obs_padding_mask"] > 0.5
    actions = th.rand(20, 24) * 2 - 1
    values, log_prob, _ = evaluate(policy, obs, actions, train=False)
    changed = _copy(obs)
    changed["proprioceptive"][padded] = float("nan")
    changed["context"][padded] = float("inf")
    values2, log_prob2, _ = evaluate(policy, changed, actions, train=False)
    assert th.allclose(values, values2, atol=1e-5) and th.allclose(log_prob, log_prob2, atol=1e-5)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_the_update_runs_on_real_tokens_only_and_equals_the_padded_pass(variant):
    """While autograd records (the PPO update), the Transformer's projections see only the real
    tokens, and the loss and every gradient equal those of the pass over all padded slots."""
    from sb3_divmorph.nn.transformer import TransformerEncoder

    policy = make_policy(variant)
    obs = batch(policy)
    actions = th.rand(20, 24) * 2 - 1
    encoders = [m for m in policy.modules() if isinstance(m, TransformerEncoder)]  # the router's too
    rows_seen: list[int] = []
    for encoder in (m.encoder for m in policy.modules() if hasattr(m, "exteroception")):  # the actor's and critic's
        encoder.layers[0].ff_in.register_forward_hook(lambda _m, inputs, _o: rows_seen.append(inputs[0].numel() // inputs[0].shape[-1]))

    def update(pack: bool):
        for encoder in encoders:
            encoder.pack_tokens = pack
        rows_seen.clear()
        values, log_prob, entropy = evaluate(policy, obs, actions, train=True)
        loss = -log_prob.mean() + 0.5 * values.pow(2).mean() - 0.01 * entropy.mean()
        policy.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in policy.parameters() if p.grad is not None], set(rows_seen)

    packed_loss, packed, packed_rows = update(True)
    padded_loss, padded, padded_rows = update(False)
    assert packed_rows == {int((obs["obs_padding_mask"] < 0.5).sum())} and padded_rows == {20 * contract.MAX_TOKENS}
    assert th.allclose(packed_loss, padded_loss, atol=1e-6) and len(packed) == len(padded)
    for a, b in zip(packed, padded):
        assert th.allclose(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_rollout_steps_act_as_the_recorded_pass_and_hand_out_ordinary_tensors(variant):
    """A rollout step (``forward`` under no_grad, the policy in eval mode, run in inference mode) samples the same
    actions for the same observations and seed as the pass autograd records, with the same values and
    log-probabilities, and ``predict`` (also in inference mode) the same deterministic actions; what it returns is an ordinary tensor a loss may use, and the update after it (its Cayley
    solve reading indices first made in the rollout) trains (broken twice: outputs not cloned out of inference
    mode -> the loss fails; the index cache made inside it -> the update fails)."""
    from sb3_divmorph.nn.layers import _upper_indices

    _upper_indices.cache_clear()
    policy = make_policy(variant)
    obs = batch(policy)
    policy.set_training_mode(False)
    th.manual_seed(7)
    with th.no_grad():
        actions, values, log_prob = policy(obs)
    th.manual_seed(7)
    recorded = [t.detach() for t in policy(obs)]
    for lean, reference in zip((actions, values, log_prob), recorded):
        th.testing.assert_close(lean, reference, rtol=1e-5, atol=1e-6)
        assert not lean.is_inference()
    th.manual_seed(7)
    predicted = th.as_tensor(policy.predict({k: v.numpy() for k, v in obs.items()}, deterministic=True)[0])
    th.testing.assert_close(predicted, policy.get_distribution(obs).get_actions(deterministic=True).detach().clamp(-1, 1))
    policy.set_training_mode(True)
    new_values, new_log_prob, _ = policy.evaluate_actions(obs, actions)
    loss = (new_values - values).pow(2).mean() - (new_log_prob - log_prob).exp().mean()
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.parameters())


TOWER_CASES = {
    "metamorph": ("metamorph", {}),
    "metamorph-no-decoder-no-extero": ("metamorph", dict(net_arch=dict(pi=[], vf=[]), exteroception={})),
    "divmorph": ("divmorph", {}),
    "divmorph-lowrank-diverted-extero-adapter": ("divmorph", dict(n_learngenes=1, divert_exteroception=True, adapter_rank=2)),
    "divmorph-no-decoder-no-extero": ("divmorph", dict(net_arch=dict(pi=[], vf=[]), exteroception={})),
}


@pytest.mark.parametrize("case", list(TOWER_CASES))
def test_a_rollout_step_runs_both_towers_as_one_pass_with_the_same_results(monkeypatch, case):
    """A rollout step computes actor and critic in one stacked pass (FusedTowers), a DivMorph actor's gated layers
    as per-sample weights, what the robots fix (padding, mask, the context's embedding) once per robot: the same
    actions, values and log-probabilities as the towers run one after the other; after an update changes the
    weights, and when the batch's robots change (new gates, new context), it follows them (broken five times: the
    towers' weights swapped in the stack -> values differ; the stack cached regardless of the weights' versions,
    or of the gates -> the later steps fail; the robots' constants kept regardless of the weights, or of the
    context -> the later steps fail)."""
    from sb3_divmorph.nn.fused import FusedTowers

    variant, overrides = TOWER_CASES[case]
    policy = make_policy(variant, **overrides)
    if variant == "divmorph":
        with th.no_grad():  # an adapter starts at zero: give it a value so that leaving it out would show
            for layer in policy.modules():
                if isinstance(layer, FactorizedLinear) and layer.adapter_rank:
                    layer.adapter_up.normal_(0.0, 0.3)
    calls = []
    real = FusedTowers.latents
    monkeypatch.setattr(FusedTowers, "latents", lambda self, o, g=None: calls.append(1) or real(self, o, g))
    policy.set_training_mode(False)

    def step(obs, fuse: bool):
        policy.fuse_rollout_towers = fuse
        th.manual_seed(3)
        with th.no_grad():
            return policy(obs)

    # the same robots before and after an update, then new robots (new gates) with the same weights, then robots
    # that differ from those only in their context (the same padding)
    for robots, update_after in ((0, True), (0, False), (1, False), ("context moved", False)):
        obs = batch(policy, seed=1) if robots == "context moved" else batch(policy, seed=robots)
        if robots == "context moved":
            obs["context"] = obs["context"] + 0.3
        for fused, separate in zip(step(obs, True), step(obs, False)):
            th.testing.assert_close(fused, separate, rtol=1e-5, atol=1e-5)
        if update_after:
            with th.no_grad():  # what an optimiser step does to the towers between two rollouts (gates kept)
                for name, p in policy.named_parameters():
                    if not name.startswith("router."):
                        p.add_(0.05 * th.randn_like(p))
    assert len(calls) == 4


def test_a_large_gated_batch_runs_the_towers_one_after_the_other(monkeypatch):
    """Per-sample weights of a gated actor grow with the batch (a GPU rollout of thousands of worlds would hold
    gigabytes): above ``max_per_sample_batch`` samples the towers run one after the other, with the same results;
    a dense actor's stacked weights do not grow, and MetaMorph keeps the one pass (broken once: the limit ignored
    -> the stacked pass is called for the large DivMorph batch)."""
    from sb3_divmorph.nn.fused import FusedTowers

    calls = []
    real = FusedTowers.latents
    monkeypatch.setattr(FusedTowers, "latents", lambda self, o, g=None: calls.append(1) or real(self, o, g))
    monkeypatch.setattr(FusedTowers, "max_per_sample_batch", 8)
    for variant, expected_calls in (("divmorph", 0), ("metamorph", 1)):
        calls.clear()
        policy = make_policy(variant)
        obs = batch(policy, size=20)
        policy.set_training_mode(False)
        th.manual_seed(3)
        with th.no_grad():
            first = policy(obs)
        policy.fuse_rollout_towers = False
        th.manual_seed(3)
        with th.no_grad():
            separate = policy(obs)
        for a, b in zip(first, separate):
            th.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
        assert len(calls) == expected_calls, variant


@pytest.mark.parametrize("variant", ["metamorph", "divmorph"])
def test_the_update_keeps_the_towers_apart_and_its_gradients_do_not_depend_on_the_rollout_pass(monkeypatch, variant):
    """Training passes never take the stacked path (per-tower learning rates and freezing need each tower's own
    parameters): with the fused rollout pass on or off, the update's loss and every gradient are the same, and
    the stacked pass is not called under autograd (broken once: ``_fused_towers`` allowed under autograd -> the
    stacked weights are detached, the towers get no gradient and the call is counted)."""
    from sb3_divmorph.nn.fused import FusedTowers

    calls = []
    real = FusedTowers.latents
    monkeypatch.setattr(FusedTowers, "latents", lambda self, o, g=None: calls.append(1) or real(self, o, g))
    gradients = []
    for fuse in (True, False):
        policy = make_policy(variant)
        policy.fuse_rollout_towers = fuse
        obs = batch(policy)
        policy.set_training_mode(False)
        with th.no_grad():
            actions, _, _ = policy(obs)  # a rollout step first, as PPO does
        policy.set_training_mode(True)
        values, log_prob, _ = policy.evaluate_actions(obs, actions)
        (values.square().mean() - log_prob.mean()).backward()
        gradients.append({name: p.grad.clone() for name, p in policy.named_parameters() if p.grad is not None})
    assert gradients[0].keys() == gradients[1].keys() and len(gradients[0]) > 10
    for name, grad in gradients[0].items():
        th.testing.assert_close(grad, gradients[1][name], msg=name)
    assert len(calls) == 1  # the one fused rollout step


def test_a_diverged_policy_is_named_by_its_update_and_a_rollout_step_skips_the_checks():
    """A rollout step skips the Gaussian's argument checks (a device sync each; the env refuses a non-finite action
    and names it), the update keeps them: a NaN weight fails the update with torch's message (broken once: the
    checks skipped everywhere -> the update gives NaN silently)."""
    policy = make_policy("metamorph")
    obs = batch(policy)
    with th.no_grad():
        policy.action_net.weight.fill_(float("nan"))
    policy.set_training_mode(False)
    with th.no_grad():
        actions, _, _ = policy(obs)
    assert th.isnan(actions).any()
    policy.set_training_mode(True)
    with pytest.raises(ValueError, match="constraint"):
        policy.evaluate_actions(obs, th.zeros(20, 24))


def test_only_two_towers_of_the_same_sizes_with_a_dense_critic_run_as_one():
    from sb3_divmorph.nn.fused import FusedTowers

    assert FusedTowers.of(make_policy("metamorph")) is not None
    assert FusedTowers.of(make_policy("divmorph")) is not None
    for variant in ("metamorph-shared", "divmorph-shared", "divmorph-critic"):
        assert FusedTowers.of(make_policy(variant)) is None, variant
    assert FusedTowers.of(make_policy("metamorph", net_arch=dict(pi=[16], vf=[8]))) is None


def test_a_batch_of_padding_alone_runs_as_the_padded_pass_does():
    """Token packing has nothing to pack when every slot is padding (a minibatch of empty samples):
    the encoder under autograd then gives what the padded pass gives, and gradients flow (break:
    drop the guard -> every output differs from the padded pass's)."""
    from sb3_divmorph.nn.transformer import TransformerEncoder

    th.manual_seed(0)
    encoder = TransformerEncoder(16, 2, 2, 32)
    x = th.randn(3, contract.MAX_TOKENS, 16, requires_grad=True)
    empty = th.ones(3, contract.MAX_TOKENS, dtype=th.bool)
    packed = encoder(x, empty)
    encoder.pack_tokens = False
    padded = encoder(x, empty)
    th.testing.assert_close(packed, padded, equal_nan=True)
    packed.nan_to_num().sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_mixed_batch_equals_per_sample_evaluation(variant):
    policy = make_policy(variant)
    obs = batch(policy, size=20)  # 4 robots x 3 tasks, above the router's deduplication threshold
    actions = th.rand(20, 24) * 2 - 1
    for train in (True, False):
        values, log_prob, entropy = evaluate(policy, obs, actions, train)
        for i in range(20):
            single = {key: value[i : i + 1] for key, value in obs.items()}
            v, lp, ent = evaluate(policy, single, actions[i : i + 1], train)
            assert th.allclose(v, values[i : i + 1], atol=1e-5)
            assert th.allclose(lp, log_prob[i : i + 1], atol=1e-4)
            assert th.allclose(ent, entropy[i : i + 1])


def test_value_is_masked_mean_of_token_values():
    policy = make_policy("metamorph")
    obs = batch(policy)
    policy.set_training_mode(False)
    with th.no_grad():
        _, latent_vf, _ = policy._latents(policy._preprocess(obs), actor=False)
        per_token = policy.value_net(latent_vf)[..., 0]
        real = obs["obs_padding_mask"] < 0.5
        expected = (per_token * real).sum(1) / real.sum(1)
        assert th.allclose(policy.predict_values(obs)[:, 0], expected, atol=1e-6)


# -- gates ---------------------------------------------------------------------------------------
def test_gate_activations_for_analysis():
    policy = make_policy("divmorph")
    obs_np = random_observations(SPACE, 24, seed=3, n_morphologies=4, n_tasks=2)
    gates = policy.get_gates(obs_np)
    assert gates.morphology.shape == (24, 3) and gates.task.shape == (24, 3)
    for weights, k in ((gates.morphology, 2), (gates.task, 2)):
        assert th.all((weights > 0).sum(-1) == k)
        assert th.allclose(weights.sum(-1), th.ones(24), atol=1e-6)
    # gates depend on the robot (context) and the task only
    context = obs_np["context"].reshape(24, -1)
    same_robot = np.all(context[:, None] == context[None], axis=-1)
    morph = gates.morphology.numpy()
    assert np.allclose(morph[same_robot.nonzero()[0]], morph[same_robot.nonzero()[1]], atol=1e-6)
    assert len({tuple(np.round(row, 5)) for row in morph}) > 1


@pytest.mark.parametrize("diversion", sorted(sb3_divmorph.policies.DIVERSIONS))
def test_every_named_diversion_trains_its_gates_and_morphology_encoder(diversion):
    """The policy loss reaches both gates' scorers and the morphology encoder, top-1 gates included
    (``deploy-g2k1``, ``deploy-g1k1``: a softmax over one kept score is the constant 1, so without the
    straight-through weight of :class:`~sb3_divmorph.nn.gates.TopKSoftGate` they got exactly 0)."""
    # the named diversion decides tailor counts and top-k (TINY_DIVMORPH's own are for "default")
    named = {} if diversion == "default" else dict(n_morph_tailors=None, n_task_tailors=None, top_k_morph=None, top_k_task=None)
    policy = make_policy("divmorph", diversion=diversion, **named)
    obs = batch(policy, size=12, n_morphologies=4, n_tasks=3)
    gates = policy.get_gates(obs)
    k = policy.config["top_k_morph"], policy.config["top_k_task"]
    for weights, kept in zip(gates, k):
        assert th.all((weights > 0).sum(-1) == kept) and th.allclose(weights.sum(-1), th.ones(len(weights)))  # forward unchanged
    actions = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (12, 24)).astype(np.float32))
    _, log_prob, _ = policy.evaluate_actions(obs, actions)
    policy.optimizer.zero_grad()
    (-log_prob.mean()).backward()
    router = policy.router
    for name, module in (
        ("morphology gate", router.morphology_gate),
        ("task gate", router.task_gate),
        ("morphology encoder", router.morphology_encoder),
    ):
        norm = sum(float(p.grad.abs().sum()) for p in module.parameters() if p.grad is not None)
        assert norm > 0, f"{diversion}: no gradient reaches the {name}"


# -- PPO: save / load, learning ------------------------------------------------------------------
class StandInEnv(gym.Env):
    """Tiny env with the contract spaces: each robot must output a fixed target on its hinges."""

    def __init__(self, n_robots: int = 2, episode_length: int = 16):
        self.observation_space = contract.observation_space()
        self.action_space = contract.action_space()
        self.robots = random_observations(self.observation_space, n_robots, seed=7, n_tasks=1)
        self.targets = 0.5 * np.sign(np.repeat(self.robots["context"][:, :, :1], 2, axis=2).reshape(n_robots, -1))
        self.episode_length = episode_length

    def _obs(self):
        obs = {key: value[self._robot].copy() for key, value in self.robots.items()}
        obs["proprioceptive"] = np.where(
            obs["obs_padding_mask"][:, None] > 0.5, 0.0, self.np_random.normal(size=obs["proprioceptive"].shape)
        ).astype(np.float32)
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._robot, self._t = int(self.np_random.integers(len(self.targets))), 0
        return self._obs(), {}

    def step(self, action):
        real = self.robots["act_padding_mask"][self._robot] < 0.5
        error = (np.clip(action, -1, 1) - self.targets[self._robot])[real]
        self._t += 1
        return self._obs(), float(-np.mean(error**2)), False, self._t >= self.episode_length, {}


@pytest.mark.parametrize("variant", ["metamorph", "divmorph"])
def test_save_load_roundtrip(tmp_path, variant):
    cls, kwargs = VARIANTS[variant]
    model = PPO(cls.__name__, StandInEnv(), n_steps=32, batch_size=16, n_epochs=1, policy_kwargs=kwargs, seed=0)
    model.learn(64)
    model.save(tmp_path / "model")
    loaded = PPO.load(tmp_path / "model", device="cpu")
    assert type(loaded.policy) is cls
    original, restored = model.policy.state_dict(), loaded.policy.state_dict()
    assert original.keys() == restored.keys()
    assert all(th.equal(original[key], restored[key]) for key in original)
    obs = random_observations(SPACE, 8, seed=5)
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    # policy-level save / load (SB3's _get_constructor_parameters) as well
    model.policy.save(tmp_path / "policy.pth")
    policy = cls.load(tmp_path / "policy.pth")
    assert np.array_equal(model.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0])


@pytest.mark.parametrize("variant", ["metamorph", "divmorph"])
def test_mixed_precision_runs_the_transformer_in_bfloat16_and_keeps_the_rest_float32(tmp_path, variant):
    cls, kwargs = VARIANTS[variant]
    model = PPO(cls.__name__, StandInEnv(), n_steps=32, batch_size=16, n_epochs=1, policy_kwargs=dict(kwargs, mixed_precision=True), seed=0)
    obs = batch(model.policy, 16)
    dtypes: set = set()
    hooks = [
        module.register_forward_hook(lambda _m, _i, out: dtypes.add(out.dtype) if isinstance(out, th.Tensor) else None)
        for module in model.policy.pi_features_extractor.encoder.modules()
    ]
    with th.no_grad():
        mixed = model.policy.get_distribution(obs).distribution.mean
        seen_mixed, dtypes = dtypes, set()
        model.policy.mixed_precision = False
        full = model.policy.get_distribution(obs).distribution.mean
    for hook in hooks:
        hook.remove()
    assert th.bfloat16 in seen_mixed and th.bfloat16 not in dtypes, "the Transformer's layers run in bfloat16 only when asked"
    assert mixed.dtype == th.float32, "the heads and the distribution stay float32"
    gap = (mixed - full).abs().max().item()
    assert 0 < gap < 0.05, f"bfloat16 rounding moves the action means a little, not {gap}"
    model.policy.mixed_precision = True
    model.learn(32)
    model.save(tmp_path / "model")
    assert PPO.load(tmp_path / "model", device="cpu").policy.mixed_precision, "the setting is saved with the model"


def test_mixed_precision_is_refused_where_it_is_not_implemented():
    from sb3_divmorph import ModuMorphPolicy

    with pytest.raises(ValueError, match="does not support mixed_precision"):
        ModuMorphPolicy(SPACE, ACTION_SPACE, lambda _: 3e-4, **TINY, mixed_precision=True)


def test_learned_std_trains():
    model = PPO(
        DivMorphPolicy,
        StandInEnv(),
        n_steps=32,
        batch_size=16,
        n_epochs=2,
        policy_kwargs=dict(TINY_DIVMORPH, learn_std=True, action_std=0.5),
        seed=0,
    )
    initial = model.policy.log_std.detach().clone()
    assert isinstance(model.policy.log_std, th.nn.Parameter) and th.allclose(initial.exp(), th.full((24,), 0.5))
    model.learn(64)
    assert not th.equal(model.policy.log_std.detach(), initial)


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("variant", ["metamorph", "divmorph"])
def test_runs_on_gpu(variant):
    cls, kwargs = VARIANTS[variant]
    model = PPO(cls, StandInEnv(), n_steps=32, batch_size=16, n_epochs=1, policy_kwargs=kwargs, device="auto")
    assert model.policy.device.type == "cuda"
    model.learn(64)


# Two default training robots; FT returns early in training are dominated by how a robot topples,
# which a few thousand PPO steps already improve clearly (measured on seeds 0-3 of both policies:
# every seed gains >= 9 on the score below; seeds 0 and 1 gain 14-17).
FT_MORPHOLOGIES = ("train-000", "train-001")
FT_STEPS = 8000
FT_MARGIN = 5.0


class _EpisodeReturns(BaseCallback):
    def __init__(self):
        super().__init__()
        self.returns: list[float] = []

    def _on_step(self) -> bool:
        self.returns += [info["episode"]["r"] for info in self.locals["infos"] if "episode" in info]
        return True


def _ft_improvement(policy: str, seed: int) -> float:
    """Mean of two gains: deterministic evaluation after vs before training (6 episodes from fixed
    starts) and the mean return of the last vs the first quarter of the training episodes."""
    from stable_baselines3.common.evaluation import evaluate_policy

    import unimal_envs

    folder = Path(unimal_envs.__file__).parent / "data" / "morphologies" / "train" / "xml"
    xml = [str(folder / f"{name}.xml") for name in FT_MORPHOLOGIES]
    venv = VecMonitor(DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=xml, max_episode_steps=200)] * 2))
    venv = VecNormalize(venv, norm_obs_keys=["proprioceptive"])
    kwargs = dict(d_model=32, n_layers=1, n_heads=2, ff_dim=64, exteroception={}, net_arch=dict(pi=[32], vf=[32]))
    if policy == "DivMorphPolicy":
        kwargs.update(n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2, morph_embed_dim=16, gate_hidden_dim=16)
    model = PPO(policy, venv, n_steps=256, batch_size=128, n_epochs=5, learning_rate=1e-3, policy_kwargs=kwargs, seed=seed)

    def evaluate() -> float:
        venv.training = False
        venv.seed(123)
        mean, _ = evaluate_policy(model, venv, n_eval_episodes=6, deterministic=True)  # raw returns (VecMonitor)
        venv.training = True
        return float(mean)

    before = evaluate()
    returns = _EpisodeReturns()
    model.learn(FT_STEPS, callback=returns)
    after = evaluate()
    quarter = max(len(returns.returns) // 4, 1)
    rollout_gain = np.mean(returns.returns[-quarter:]) - np.mean(returns.returns[:quarter])
    return float((after - before + rollout_gain) / 2)


@pytest.mark.parametrize("policy", ["MetaMorphPolicy", "DivMorphPolicy"])
def test_ppo_improves_return_on_flat_terrain(policy):
    gains = [_ft_improvement(policy, seed) for seed in (0, 1)]
    assert min(gains) > FT_MARGIN, gains


@pytest.mark.parametrize("policy", [MetaMorphPolicy, DivMorphPolicy])
def test_trains_on_multitask_and_routes_tasks_apart(policy):
    """One PPO run over the five training tasks; DivMorph's task gates then differ between tasks."""
    import unimal_envs
    from unimal_envs.morphology.loader import morphology_files

    th.manual_seed(0)
    files = morphology_files("train")[:2]
    envs = [lambda: gym.make("Unimal-MultiTask-v1", morphologies=files) for _ in range(2)]
    venv = VecNormalize(DummyVecEnv(envs), norm_obs_keys=["proprioceptive"])
    venv.seed(0)
    model = PPO(policy, venv, n_steps=128, batch_size=128, n_epochs=1, seed=0)
    model.learn(256)
    if policy is DivMorphPolicy:
        env = unimal_envs.MultiTaskEnv(morphologies=files)
        obs = [env.reset(seed=0, options={"task": task, "morphology": 0})[0] for task in contract.TRAIN_TASKS]
        batch = {k: th.as_tensor(np.stack([o[k] for o in obs])) for k in obs[0]}
        gates = model.policy.get_gates(batch)
        assert th.allclose(gates.morphology[0], gates.morphology[1])  # same robot, same morphology gate
        assert not th.allclose(gates.task[0], gates.task[1])  # FT and VT route to different task tailors


def test_trpo_trains_a_policy_under_the_math_attention_kernel():
    """TRPO differentiates twice (Hessian-vector products); under PyTorch's math attention kernel, as
    docs/policies.md says, it updates the policy (the fused kernel cannot: its error is documented)."""
    sb3_contrib = pytest.importorskip("sb3_contrib")
    from torch.nn.attention import SDPBackend, sdpa_kernel

    model = sb3_contrib.TRPO(MetaMorphPolicy, StandInEnv(), n_steps=64, batch_size=32, policy_kwargs=TINY, seed=0)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    with sdpa_kernel(SDPBackend.MATH):
        model.learn(64)
    assert any(not th.equal(before[k], v) for k, v in model.policy.state_dict().items())
