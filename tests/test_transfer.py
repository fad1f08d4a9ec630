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
import unimal_envs
from sb3_divmorph.algos.finetune import (
    UnitLearningRates,
    UnitSelection,
    actor_modules,
    critic_modules,
    critic_rate_scales,
    prepare_transfer,
)
from sb3_divmorph.nn.layers import FactorizedLinear
from unimal_envs.morphology.loader import morphology_files

TINY_DIVMORPH = dict(
    d_model=16,
    n_layers=1,
    ff_dim=32,
    exteroception=dict(hfield=[8], goal=[4], object=[4]),
    n_morph_tailors=6,
    n_task_tailors=6,
    top_k_morph=2,
    top_k_task=2,
)
ROBOTS = morphology_files("train")[:2]


def distilled_like_student(seed: int = 0, **ppo_kwargs) -> tuple[PPO, VecNormalize]:
    """A tiny DivMorph PPO on Escape whose square factors have been rotated (skew != 0), as after
    distillation."""
    th.manual_seed(seed)
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make("Unimal-Escape-v0", morphologies=ROBOTS, max_episode_steps=50)]), norm_obs_keys=["proprioceptive"]
    )
    kwargs = dict(n_steps=64, batch_size=16, n_epochs=5, learning_rate=3e-3, seed=seed)
    model = PPO("DivMorphPolicy", venv, **{"policy_kwargs": TINY_DIVMORPH, **kwargs, **ppo_kwargs})
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
    assert not 0.07 <= ratio_after_tiny_steps(model, obs, rates, "learngene") <= 0.14


def ratio_after_tiny_steps(model, obs, rates, numerator: str) -> float:
    """Update ratio (``numerator`` / selected tailors) after 20 tiny imitation steps on ``obs``."""
    batch = {k: np.repeat(v, 32, axis=0) for k, v in obs.items()}
    obs_t, _ = model.policy.obs_to_tensor(batch)
    actions = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (32, 24)).astype(np.float32))
    for _ in range(20):
        loss = -model.policy.get_distribution(obs_t).log_prob(actions).mean() * 1e-5
        model.policy.optimizer.zero_grad()
        loss.backward()
        model.policy.optimizer.step()
    return rates.measured_ratio(numerator=numerator)


@pytest.mark.parametrize("undiverted_scale, expected", [(1.0, 1.0), (None, 0.1)])
def test_a_part_an_ablation_does_not_divert_trains_at_the_full_rate_unless_asked(undiverted_scale, expected):
    """``no-kdiv-transformer``: the Transformer has no tailors, so every unit of it was a learngene
    and trained 10x slower than DivMorph's selected tailors, confounding the ablation with a learning
    rate. By default it now trains at the full rate (the selected tailors' rate); ``None`` keeps the
    former rule (``learngene_scale``)."""
    model, venv = distilled_like_student(seed=2, policy_kwargs={**TINY_DIVMORPH, "divert_transformer": False})
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    rates = prepare_transfer(model.policy, selection, learngene_scale=0.1, undiverted_scale=undiverted_scale)
    measured = ratio_after_tiny_steps(model, obs, rates, "undiverted")
    assert 0.7 * expected <= measured <= 1.4 * expected, f"undiverted / selected tailor update ratio {measured:.3f}, expected {expected}"
    assert 0.07 <= rates.measured_ratio() <= 0.14  # the decoder's learngenes keep their rate


@pytest.mark.parametrize("ablation, expected", [({"divert_transformer": False}, 1.0), ({"divert_decoder": False}, 1.0), ({}, 0.1)])
def test_outside_its_diverted_parts_an_ablation_trains_as_the_dense_student(ablation, expected):
    """The token embedding and exteroception encoders: shared knowledge at the learngene rate in DivMorph, an
    ordinary fine-tuned network at the full rate in an ablation (as in the dense student), so that an
    ablation differs from DivMorph in its diversion and not in these rates (broken by giving them
    ``learngene_scale`` in every policy: the ablations' ratio falls to 0.1)."""
    model, venv = distilled_like_student(seed=2, policy_kwargs={**TINY_DIVMORPH, **ablation})
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    rates = prepare_transfer(model.policy, selection, learngene_scale=0.1)
    extractor = model.policy.features_extractor
    embedding = next(p for name, p in extractor.named_parameters() if "embed" in name and p.dim() == 2)
    before = embedding.detach().clone()
    ratio_after_tiny_steps(model, obs, rates, "learngene")  # 20 steps of one fixed loss: each moves a weight by ~its rate
    per_step = (embedding.detach() - before).abs().mean().item() / 20
    measured = per_step / rates.mean_updates()["selected_tailor"]
    assert 0.6 * expected <= measured <= 1.5 * expected, f"embedding / selected tailor update ratio {measured:.3f}, expected {expected}"
    assert 0.07 <= rates.measured_ratio() <= 0.14  # the diverted part's learngenes keep their rate


def one_ppo_like_step(model, obs) -> dict[str, th.Tensor]:
    """The parameters after one optimiser step on a loss of both heads (log-likelihood of fixed actions + value)."""
    batch = {k: np.repeat(v, 16, axis=0) for k, v in obs.items()}
    obs_t, _ = model.policy.obs_to_tensor(batch)
    actions = th.as_tensor(np.random.default_rng(0).uniform(-1, 1, (16, 24)).astype(np.float32))
    values, log_prob, _ = model.policy.evaluate_actions(obs_t, actions)
    model.policy.optimizer.zero_grad()
    (-log_prob.mean() + (values - 1.0).pow(2).mean()).backward()
    model.policy.optimizer.step()
    return {name: p.detach().clone() for name, p in model.policy.named_parameters()}


@pytest.mark.parametrize("divmorph_way", [False, True])
def test_critic_lr_scale_moves_the_critic_that_many_times_as_far_and_the_actor_as_before(divmorph_way):
    """transfer.critic_lr_scale: a fine-tuned actor at its small rate, its critic at a multiple of it."""
    moved = {}
    for scale in (1.0, 10.0):
        model, venv = distilled_like_student(seed=3)
        obs = venv.reset()
        if divmorph_way:
            gates = model.policy.get_gates(obs)
            selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
            prepare_transfer(model.policy, selection, learngene_scale=0.1, critic_scale=scale)
        else:
            UnitLearningRates(model.policy.optimizer, critic_rate_scales(model.policy, scale))
        before = {name: p.detach().clone() for name, p in model.policy.named_parameters()}
        after = one_ppo_like_step(model, obs)
        moved[scale] = {name: (after[name] - before[name]).abs().sum().item() for name in before}
    critic = {id(p) for module in critic_modules(model.policy) for p in module.parameters()}
    names = {name: id(p) in critic for name, p in model.policy.named_parameters()}
    critic_ratio = sum(moved[10.0][n] for n, c in names.items() if c) / sum(moved[1.0][n] for n, c in names.items() if c)
    assert critic_ratio == pytest.approx(10.0, rel=1e-3), f"the critic moved {critic_ratio:.3f}x as far"
    assert all(moved[10.0][n] == pytest.approx(moved[1.0][n], rel=1e-5, abs=1e-9) for n, c in names.items() if not c), (
        "the actor's steps changed"
    )


def test_frozen_observation_statistics_stay_while_reward_statistics_learn(tmp_path):
    from sb3_divmorph.algos.finetune import freeze_observation_statistics, observation_statistics_frozen

    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=ROBOTS, max_episode_steps=50)]), norm_obs_keys=["proprioceptive"]
    )
    venv.reset()
    for _ in range(5):
        venv.step(np.zeros((1, 24), dtype=np.float32))
    freeze_observation_statistics(venv)
    mean, var, count = (
        venv.obs_rms["proprioceptive"].mean.copy(),
        venv.obs_rms["proprioceptive"].var.copy(),
        venv.obs_rms["proprioceptive"].count,
    )
    returns_count = venv.ret_rms.count
    raw = venv.get_original_obs()
    normalised = venv.normalize_obs(raw)["proprioceptive"].copy()
    rng = np.random.default_rng(0)
    for _ in range(20):
        venv.step(rng.uniform(-1, 1, (1, 24)).astype(np.float32))
    venv.reset()
    assert venv.training and venv.ret_rms.count == returns_count + 20  # rewards still learn
    stats = venv.obs_rms["proprioceptive"]
    assert np.array_equal(stats.mean, mean) and np.array_equal(stats.var, var) and stats.count == count
    assert np.array_equal(venv.normalize_obs(raw)["proprioceptive"], normalised)
    venv.save(str(tmp_path / "vecnormalize.pkl"))  # a checkpoint (or a resumed run) keeps them frozen
    loaded = VecNormalize.load(str(tmp_path / "vecnormalize.pkl"), venv.venv)
    assert observation_statistics_frozen(loaded)
    loaded.reset()
    assert np.array_equal(loaded.obs_rms["proprioceptive"].mean, mean)


@pytest.mark.parametrize("task, keys", [("Escape", ["hfield"]), ("PushBoxIncline", ["object", "goal"]), ("PointNav", ["goal"])])
def test_a_teacher_without_an_encoder_for_a_task_input_gets_one_and_keeps_its_weights(task, keys):
    """MetaMorph→ from an FT teacher (no exteroception encoders) must see Escape's height map,
    PushBoxIncline's box and goal: the encoders the task's own architecture has are added freshly
    initialised; every trained weight is kept (the decoder's first layer column by column)."""
    from divmorph.pipeline.transfer import finetuned_model

    tiny = dict(d_model=16, n_layers=1, ff_dim=32)
    th.manual_seed(0)
    teacher = PPO(
        "MetaMorphPolicy",
        DummyVecEnv([lambda: gym.make("Unimal-FT-v0", morphologies=ROBOTS)]),
        policy_kwargs={**tiny, "exteroception": {}},
        n_steps=64,
        batch_size=64,
    )
    venv = DummyVecEnv([lambda: gym.make(unimal_envs.env_id(task), morphologies=ROBOTS)])
    model = finetuned_model(
        teacher, venv, task, {**tiny, "exteroception": dict(hfield=[8], goal=[4], object=[4])}, 0, "cpu", dict(n_steps=64, batch_size=64)
    )
    assert sorted(model.policy.pi_features_extractor.exteroception) == sorted(keys)
    old, new = teacher.policy.state_dict(), model.policy.state_dict()
    for name, value in old.items():
        target = new[name]
        assert th.equal(target[:, : value.shape[1]] if target.shape != value.shape else target, value), name
    obs = venv.reset()
    actions = model.predict(obs, deterministic=True)[0]
    for key in keys:
        changed = {k: v.copy() for k, v in obs.items()}
        changed[key] = changed[key] + np.random.default_rng(1).normal(0, 1, changed[key].shape).astype(np.float32)
        assert np.abs(model.predict(changed, deterministic=True)[0] - actions).max() > 1e-6, f"{task}: blind to {key}"


def test_rotation_lr_scale_turns_the_square_factors_that_much_slower_and_moves_the_rest_as_before():
    """transfer.rotation_lr_scale: the Cayley generators, whose full-rate steps dominate a DivMorph
    student's update, move ``scale`` times as far; the tall factors and singular values as before."""
    moved = {}
    for scale in (1.0, 0.1, 0.0):
        model, venv = distilled_like_student(seed=4)
        obs = venv.reset()
        gates = model.policy.get_gates(obs)
        selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
        prepare_transfer(model.policy, selection, learngene_scale=1.0, rotation_scale=scale)
        layers = diverted_actor_layers(model.policy)
        squares = [layer.square_factor().detach().clone() for layer in layers]
        before = {name: p.detach().clone() for name, p in model.policy.named_parameters()}
        after = one_ppo_like_step(model, obs)
        moved[scale] = {name: (after[name] - before[name]).abs().sum().item() for name in before}
        if scale == 0.0:  # the policy's square factors stay exactly where transfer re-based them
            assert all(th.equal(layer.square_factor().detach(), old) for layer, old in zip(layers, squares))
    skews = [name for name in moved[1.0] if name.endswith("square_skew") and moved[1.0][name] > 0]
    assert skews, "no Cayley generator moved at the full rate"
    for name in skews:
        assert moved[0.1][name] == pytest.approx(0.1 * moved[1.0][name], rel=1e-3), name
    others = [name for name in moved[1.0] if not name.endswith("square_skew")]
    assert all(moved[0.1][n] == pytest.approx(moved[1.0][n], rel=1e-5, abs=1e-9) for n in others), "the other factors' steps changed"


@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_rotation_lr_scale_0_fixes_the_free_square_factors_of_a_student_without_orthogonality(scale):
    """The ``no-orthogonality`` ablation's square factors are free matrices: at ``rotation_lr_scale`` 0 they
    stay exactly, as a DivMorph student's Cayley rotations do (the ablation race's terms), at 1 the selected
    units' columns move; the tall factors move either way (break: ignore the scale for free square factors
    -> they move at 0)."""
    model, venv = distilled_like_student(seed=7, policy_kwargs={**TINY_DIVMORPH, "orthogonal": False})
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    prepare_transfer(model.policy, selection, learngene_scale=1.0, rotation_scale=scale)
    layers = diverted_actor_layers(model.policy)
    assert layers and not any(layer.orthogonal for layer in layers)
    before = [snapshot(layer) for layer in layers]
    one_ppo_like_step(model, obs)
    after = [snapshot(layer) for layer in layers]
    squares_moved = sum((a["square"] - b["square"]).abs().sum().item() for a, b in zip(after, before))
    assert (squares_moved == 0) == (scale == 0.0)
    assert sum((a["tall"] - b["tall"]).abs().sum().item() for a, b in zip(after, before)) > 0


def test_rotation_rate_scales_freeze_a_freely_fine_tuned_students_rotations_only():
    """The ``divmorph-finetuned`` arm with ``rotation_lr_scale=0`` (issue 67 (a)): every Cayley
    generator stays exactly where it was, every other parameter moves as before (break: an empty
    ``rotation_rate_scales`` -> the generators move)."""
    from sb3_divmorph.algos.finetune import rotation_rate_scales

    model, venv = distilled_like_student(seed=5)
    obs = venv.reset()
    scales = rotation_rate_scales(model.policy, 0.0)
    assert scales and all(name.endswith("square_skew") for name, p in model.policy.named_parameters() if p in scales)
    rates = UnitLearningRates(model.policy.optimizer, scales)
    before = {name: p.detach().clone() for name, p in model.policy.named_parameters()}
    after = one_ppo_like_step(model, obs)
    rates.remove()
    for name in before:
        if name.endswith("square_skew"):
            assert th.equal(after[name], before[name]), name
    assert sum((after[n] - before[n]).abs().sum().item() for n in before if not n.endswith("square_skew")) > 0


def test_the_singular_values_recipe_trains_the_active_units_singular_values_and_nothing_else_of_the_actor():
    """``transfer.recipe: singular-values`` (FINE's rule, issue 67 (c)): after an update only the
    singular values of learngenes and selected tailors have moved in the actor (and the critic);
    tall factors, rotations, embeddings and unselected tailors stay exactly (break: ignore the recipe
    -> the tall factors move)."""
    model, venv = distilled_like_student(seed=6)
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    prepare_transfer(model.policy, selection, learngene_scale=0.1, recipe="singular-values")
    layers = diverted_actor_layers(model.policy)
    before = {name: p.detach().clone() for name, p in model.policy.named_parameters()}
    s_before = [layer.singular_values.detach().clone() for layer in layers]
    after = one_ppo_like_step(model, obs)
    actor = {id(p) for module in actor_modules(model.policy) for p in module.parameters()}
    names = {name: p for name, p in model.policy.named_parameters()}
    critic = {id(p) for module in critic_modules(model.policy) for p in module.parameters()}
    for name, p in names.items():
        if id(p) in actor and not name.endswith("singular_values") and id(p) not in critic:
            assert th.equal(after[name], before[name]), name
    moved_active = 0.0
    for layer, old in zip(layers, s_before, strict=True):
        active = th.ones(layer.rank, dtype=th.bool)
        active[layer.n_learngenes :] = th.as_tensor(selection.tailors)
        delta = (layer.singular_values.detach() - old).abs()
        assert th.all(delta[~active] == 0)  # unselected tailors stay
        moved_active += float(delta[active].sum())
    assert moved_active > 0
    assert any(not th.equal(after[n], before[n]) for n, p in names.items() if id(p) in critic)
    with pytest.raises(ValueError, match="recipe must be one of"):
        prepare_transfer(model.policy, selection, recipe="everything")


def test_the_kind_recipe_restarts_the_selected_task_tailors_and_keeps_every_other_unit():
    """``transfer.recipe: kind`` (KIND's rule for a large shift, issue 67 (c)): the selected task
    tailors get fresh unit-norm directions and zero singular values, every learngene, morphology tailor
    and unselected task tailor stays bit for bit, and one update grows the new units' singular values
    (break: skip ``reinitialise_task_tailors`` in ``prepare_transfer`` -> their singular values are not 0)."""
    model, venv = distilled_like_student(seed=7)
    obs = venv.reset()
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    layers = [layer for layer in diverted_actor_layers(model.policy) if layer.n_task_tailors]
    assert layers and selection.task.any() and not selection.task.all()
    old = [(layer.singular_values.detach().clone(), layer.tall.detach().clone()) for layer in layers]
    prepare_transfer(model.policy, selection, learngene_scale=0.1, recipe="kind")
    restarted = []
    for layer, (s_old, tall_old) in zip(layers, old, strict=True):
        task = layer.unit_slices["task"]
        units = th.arange(task.start, task.stop)[th.as_tensor(selection.task)]
        kept = th.ones(layer.rank, dtype=th.bool)
        kept[units] = False
        assert th.all(layer.singular_values.detach()[units] == 0)
        assert th.allclose(layer.tall.detach()[:, units].norm(dim=0), th.ones(len(units)), atol=1e-5)
        assert not th.allclose(layer.tall.detach()[:, units], tall_old[:, units])
        assert th.equal(layer.singular_values.detach()[kept], s_old[kept]) and th.equal(layer.tall.detach()[:, kept], tall_old[:, kept])
        restarted.append(units)
    one_ppo_like_step(model, obs)
    grown = sum(float(layer.singular_values.detach()[units].abs().sum()) for layer, units in zip(layers, restarted, strict=True))
    assert grown > 0, "the restarted task tailors learn"


def test_a_resumed_or_finished_kind_run_is_not_restarted_again():
    """``recipe: kind`` restarts the task tailors on the fresh model only: the pipeline prepares every
    model it builds *or loads* (a checkpoint, a finished run), and a second restart would throw away what
    the run learnt (break: return ``recipe`` unchanged -> a loaded run is restarted)."""
    from divmorph.pipeline.transfer import recipe_for

    assert recipe_for("kind", 0) == "kind"
    assert recipe_for("kind", 4096) == "fixed-gates"
    assert recipe_for("singular-values", 4096) == "singular-values" and recipe_for("fixed-gates", 0) == "fixed-gates"


def test_the_adapter_recipe_starts_as_the_student_and_trains_only_its_adapters():
    """``transfer.recipe: adapter`` (LoRA's rule, issue 67 (c)): the student loaded with zero-initialised
    adapters acts exactly as before; after an update every factor, bias and embedding of the actor is bit
    for bit where it was, the adapters and the critic moved, and the actions changed (break: drop
    ``adapter_scales`` from ``prepare_transfer`` -> the tall factors move; drop the adapter from
    ``FactorizedLinear.forward`` -> the actions do not change)."""
    from divmorph.pipeline.transfer import finetuned_model

    student, venv = distilled_like_student(seed=8)
    obs = venv.reset()
    obs_t, _ = student.policy.obs_to_tensor(obs)
    with th.no_grad():
        mean_student = student.policy.get_distribution(obs_t).distribution.mean.clone()
    ppo_kwargs = dict(n_steps=64, batch_size=16, n_epochs=5, learning_rate=3e-3)
    model = finetuned_model(student, venv, "Escape", TINY_DIVMORPH, 8, "cpu", ppo_kwargs, adapter_rank=2)
    layers = [m for module in actor_modules(model.policy) for m in module.modules() if isinstance(m, FactorizedLinear)]
    assert layers and all(layer.adapter_rank == 2 for layer in layers)
    with th.no_grad():
        assert th.allclose(model.policy.get_distribution(obs_t).distribution.mean, mean_student, atol=1e-5)
    gates = model.policy.get_gates(obs)
    selection = UnitSelection.from_gates(gates.morphology.numpy(), gates.task.numpy())
    prepare_transfer(model.policy, selection, learngene_scale=0.1, recipe="adapter")
    before = {name: p.detach().clone() for name, p in model.policy.named_parameters()}
    after = one_ppo_like_step(model, obs)
    actor = {id(p) for module in actor_modules(model.policy) for p in module.parameters()}
    critic = {id(p) for module in critic_modules(model.policy) for p in module.parameters()}
    for name, p in model.policy.named_parameters():
        if id(p) in actor and id(p) not in critic and not name.endswith(("adapter_down", "adapter_up")):
            assert th.equal(after[name], before[name]), name
    assert all(not th.equal(after[name], before[name]) for name in before if name.endswith("adapter_up"))
    assert any(not th.equal(after[n], before[n]) for n, p in model.policy.named_parameters() if id(p) in critic)
    with th.no_grad():
        assert not th.allclose(model.policy.get_distribution(obs_t).distribution.mean, mean_student, atol=1e-5)
    with pytest.raises(ValueError, match="adapter_rank"):
        prepare_transfer(student.policy, selection, recipe="adapter")
