"""Unit tests of the building blocks of sb3_divmorph: factorized layers, gates, Transformer."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch as th
from torch.nn import functional as F

import unimal_envs  # noqa: F401
from sb3_divmorph.nn.gates import DiversionRouter, MorphologyEncoder, TopKSoftGate
from sb3_divmorph.nn.layers import (
    DenseLinear,
    Factorization,
    FactorizedLinear,
    LayerDiversionError,
    LinearBuilder,
    batched_square_factors,
    cayley,
    project_many,
)
from sb3_divmorph.nn.transformer import TransformerEncoder
from sb3_divmorph.policies import DivMorphPolicy
from unimal_envs.morphology.loader import morphology_files

th.set_num_threads(1)

SHAPES = [(12, 12), (8, 20), (20, 8)]  # (in, out): square, wide-out (V square), narrow-out (U square)


def _gates(batch: int, n: int, seed: int = 0) -> th.Tensor:
    return th.softmax(th.randn(batch, n, generator=th.Generator().manual_seed(seed)), dim=-1)


# -- FactorizedLinear -----------------------------------------------------------------------------
@pytest.mark.parametrize("in_features,out_features", SHAPES)
@pytest.mark.parametrize("orthogonal", [True, False])
def test_factorized_layer_equals_its_dense_init(in_features, out_features, orthogonal):
    th.manual_seed(0)
    weight, bias = th.randn(out_features, in_features), th.randn(out_features)
    layer = FactorizedLinear(in_features, out_features, 2, 2, orthogonal=orthogonal, weight=weight, bias=bias)
    x = th.randn(5, 3, in_features)
    expected = F.linear(x, weight, bias)
    assert th.allclose(layer(x), expected, atol=1e-5)
    # "all units on" is also gates of ones
    assert th.allclose(layer(x, th.ones(5, layer.n_tailors)), expected, atol=1e-5)
    assert th.allclose(layer.dense_weight(), weight, atol=1e-5)
    # units are sorted by singular value, learngenes first
    s = layer.singular_values.detach()
    assert th.all(s[:-1] >= s[1:])


def test_builder_factorizes_the_same_init_as_the_dense_network():
    x = th.randn(4, 7, 16)
    th.manual_seed(3)
    dense = LinearBuilder()(16, 32)
    th.manual_seed(3)
    factorized = LinearBuilder(Factorization(4, 4))(16, 32)
    assert isinstance(dense, DenseLinear) and isinstance(factorized, FactorizedLinear)
    assert factorized.n_learngenes == 8
    assert th.allclose(factorized(x), dense(x), atol=1e-5)


def test_layers_not_meant_to_divert_keep_every_unit_a_learngene():
    head = LinearBuilder(Factorization(4, 4))(16, 2, divert=False)
    assert isinstance(head, FactorizedLinear) and head.n_tailors == 0 and head.n_learngenes == 2
    ablated = LinearBuilder(Factorization(4, 4, divert=False))(16, 16)
    assert ablated.n_tailors == 0


def test_a_layer_too_small_for_its_tailors_is_an_error_naming_it():
    with pytest.raises(LayerDiversionError, match=r"'actor decoder\.0' \(64x256, rank 64\): 56 morphology \+ 56 task"):
        LinearBuilder(Factorization(56, 56))(256, 64, name="actor decoder.0")
    # the policy refuses such a configuration instead of silently not diverting its decoder
    env = gym.make("Unimal-FT-v0", morphologies=morphology_files("train")[:1])
    with pytest.raises(LayerDiversionError, match="actor decoder.0"):
        DivMorphPolicy(
            env.observation_space,
            env.action_space,
            lambda _: 1e-3,
            d_model=128,
            n_layers=1,
            ff_dim=128,
            net_arch=dict(pi=[64], vf=[64]),
            n_morph_tailors=56,
            n_task_tailors=56,
        )


def test_per_layer_tailor_counts_fit_every_rank_and_pool_the_gate_slots():
    f = Factorization(14, 14, n_learngenes=2)
    big = LinearBuilder(f)(32, 32)
    small = LinearBuilder(f)(32, 8)
    assert (big.n_learngenes, big.n_morph_tailors, big.n_task_tailors) == (4, 14, 14)  # capped at one tailor per slot
    assert (small.n_learngenes, small.n_morph_tailors, small.n_task_tailors) == (2, 3, 3)
    # one-hot slots: slot s of the morphology gate drives tailor floor(s * 3 / 14) of the small layer
    for slot in range(14):
        gates = th.zeros(1, 28)
        gates[0, slot] = 1.0
        local = small.local_gates(gates)[0]
        assert local[:3].tolist() == [1.0 if j == slot * 3 // 14 else 0.0 for j in range(3)] and local[3:].sum() == 0
    # pooled gates still give an exact pruned layer and a working forward
    gates = th.zeros(2, 28)
    gates[:, [1, 20]] = 1.0
    x = th.randn(2, 5, 32)
    U, s, V = small.selected_units(gates[0])
    assert len(s) == 2 + 1 + 1
    assert th.allclose(small(x, gates)[0], x[0] @ V @ (U * s).T + small.bias, atol=1e-5)
    goal = LinearBuilder(Factorization(4, 4, n_learngenes=2))(3, 32, name="exteroception.goal.0")
    assert (goal.n_learngenes, goal.n_morph_tailors, goal.n_task_tailors) == (1, 1, 1)
    with pytest.raises(LayerDiversionError, match="rank 2"):
        LinearBuilder(Factorization(4, 4, n_learngenes=2))(2, 32, name="tiny")


@pytest.mark.parametrize("in_features,out_features", SHAPES)
def test_gates_scale_each_samples_tailors(in_features, out_features):
    th.manual_seed(1)
    x = th.randn(6, 4, in_features)
    gates = _gates(6, 6)
    outputs = {}
    for path in ("merged", "lowrank"):
        th.manual_seed(2)
        layer = FactorizedLinear(in_features, out_features, 3, 3, path=path)
        outputs[path] = layer(x, gates)
        for i in range(6):  # a mixed batch equals each sample with its own effective weight
            expected = F.linear(x[i], layer.dense_weight(gates[i]), layer.bias)
            assert th.allclose(outputs[path][i], expected, atol=1e-5)
    assert th.allclose(outputs["merged"], outputs["lowrank"], atol=1e-5)
    # and the gates matter: tailors at 1/k-ish weight differ from all units on
    assert not th.allclose(outputs["merged"], layer(x), atol=1e-3)


def test_zero_gates_leave_only_learngenes():
    layer = FactorizedLinear(10, 10, 2, 3)
    x = th.randn(3, 10)
    U, V = layer.factors()[:2]
    g = layer.n_learngenes
    learngene_weight = (U[:, :g] * layer.singular_values[:g]) @ V[:, :g].T
    assert th.allclose(layer(x, th.zeros(3, 5)), F.linear(x, learngene_weight, layer.bias), atol=1e-5)
    assert layer.unit_slices == {"learngene": slice(0, 5), "morphology": slice(5, 7), "task": slice(7, 10)}


def test_pruned_units_reproduce_the_gated_layer():
    th.manual_seed(0)
    layer = FactorizedLinear(16, 12, 4, 4)
    gates = th.tensor([0.7, 0.0, 0.3, 0.0, 0.0, 0.0, 1.0, 0.0])  # 2 of 4 morphology, 1 of 4 task tailors
    U, s, V = layer.selected_units(gates)
    assert U.shape[1] == layer.n_learngenes + 3
    x = th.randn(5, 16)
    assert th.allclose(F.linear(x, (U * s) @ V.T, layer.bias), layer(x, gates.expand(5, -1)), atol=1e-5)


def test_cayley_map_is_orthogonal_and_identity_at_zero():
    assert th.allclose(cayley(th.zeros(6 * 5 // 2), 6), th.eye(6))
    q = cayley(th.randn(6 * 5 // 2) * 3, 6).double()
    assert th.allclose(q.T @ q, th.eye(6, dtype=q.dtype), atol=1e-5)


def test_batched_square_factors_give_every_layer_its_own_factor_and_gradient(monkeypatch):
    th.manual_seed(0)
    layers = th.nn.ModuleList(
        [
            FactorizedLinear(8, 8, 2, 2),
            FactorizedLinear(20, 8, 2, 2),
            FactorizedLinear(8, 8, 1, 1),
            FactorizedLinear(6, 6, 1, 1, orthogonal=False),
        ]
    )
    for layer in layers:
        if layer.orthogonal:
            layer.square_skew.data.normal_(0, 0.3)  # distinct rotations: a mix-up between layers shows
    xs = [th.randn(5, layer.in_features) for layer in layers]

    def loss() -> th.Tensor:
        return sum(layer(x, _gates(5, layer.n_gates)).pow(2).sum() for layer, x in zip(layers, xs))

    expected = [layer.square_factor().detach() for layer in layers]
    reference = th.autograd.grad(loss(), list(layers.parameters()))
    solves = []
    monkeypatch.setattr(th.linalg, "solve", lambda *a, **k: solves.append(a[0].shape) or _solve(*a, **k))
    with batched_square_factors(layers):
        shared = [layer.square_factor().detach() for layer in layers]
        batched = th.autograd.grad(loss(), list(layers.parameters()))
    # one solve per rank (8 for three layers), none per layer, and the square factors and gradients of the
    # per-layer computation
    assert sorted(solves) == [(3, 8, 8)]
    for got, want in zip(shared, expected):
        assert th.allclose(got, want, atol=1e-6)
    for got, want in zip(batched, reference):
        assert th.allclose(got, want, atol=1e-5)
    assert all(layer._shared_square is None for layer in layers)  # released after the block
    with th.no_grad():  # rollouts: eval mode without autograd keeps the per-layer cache
        layers.eval()
        with batched_square_factors(layers):
            assert all(layer._shared_square is None for layer in layers)


_solve = th.linalg.solve


@pytest.mark.parametrize("in_features,out_features", SHAPES)
def test_square_factor_stays_orthogonal_under_training(in_features, out_features):
    errors = {}
    for orthogonal in (True, False):
        th.manual_seed(0)
        layer = FactorizedLinear(in_features, out_features, 2, 2, orthogonal=orthogonal)
        target = th.randn(out_features, in_features) * 3
        optimizer = th.optim.Adam(layer.parameters(), lr=0.05)
        x = th.randn(64, in_features)
        for _ in range(60):
            loss = (layer(x, _gates(64, 4)) - x @ target.T).pow(2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        errors[orthogonal] = layer.orthogonality_error()
        if orthogonal:
            assert layer.square_skew.detach().abs().max() > 1e-2  # the square factor did move
    assert errors[True] < 1e-5
    # control: the unconstrained factor drifts away, so the check above can fail
    assert errors[False] > 1e-3


def test_inference_cache_follows_parameter_updates():
    th.manual_seed(0)
    layer = FactorizedLinear(8, 8, 2, 2)
    x, gates = th.randn(3, 8), _gates(3, 4)
    layer.eval()
    with th.no_grad():
        before = layer(x, gates)
        assert th.equal(layer(x, gates), before)
        # parameters replaced while staying in eval mode (e.g. set_parameters / load_state_dict)
        state = {key: value + 0.1 * th.randn_like(value) for key, value in layer.state_dict().items()}
        layer.load_state_dict(state)
        cached = layer(x, gates)
    fresh = FactorizedLinear(8, 8, 2, 2)
    fresh.load_state_dict(state)
    assert not th.allclose(cached, before)
    assert th.allclose(cached, fresh(x, gates), atol=1e-6)
    # and after an optimizer step in train mode
    layer.train()
    optimizer = th.optim.SGD(layer.parameters(), lr=0.5)
    layer(x, gates).pow(2).sum().backward()
    optimizer.step()
    expected = layer(x, gates).detach()
    layer.eval()
    with th.no_grad():
        assert th.allclose(layer(x, gates), expected, atol=1e-6)


def test_router_inference_cache_follows_parameters_and_inputs():
    th.manual_seed(0)
    router = DiversionRouter(6, 5, 4, n_morph_tailors=6, n_task_tailors=4, top_k_morph=3, top_k_task=2, morph_embed_dim=8)
    context, tasks = th.randn(2, 5, 6), th.randn(2, 4)
    padding = th.zeros(2, 5, dtype=th.bool)
    router.eval()
    with th.no_grad():
        first = router(context, padding, tasks)
        assert th.equal(router(context.clone(), padding.clone(), tasks.clone()).morphology, first.morphology)
        other = router(context, padding, tasks.flip(0))
        assert th.equal(other.task, first.task.flip(0))
        assert th.equal(router(context, padding, tasks).morphology, first.morphology)
        router.load_state_dict({key: value + 0.3 * th.randn_like(value) for key, value in router.state_dict().items()})
        changed = router(context, padding, tasks)
    router.train()
    assert th.allclose(changed.morphology, router(context, padding, tasks).morphology, atol=1e-6)
    assert not th.allclose(changed.morphology, first.morphology)
    # a part replaced by a new module (its parameters new tensors) is seen too (broken once: the parameter list
    # kept from before -> the old gates come back)
    router.eval()
    with th.no_grad():
        router(context, padding, tasks)
        router.task_gate = TopKSoftGate(4, 4, 2, name="task gate")
        replaced = router(context, padding, tasks)
    router.train()
    assert th.allclose(replaced.task, router(context, padding, tasks).task, atol=1e-6)
    assert not th.allclose(replaced.task, changed.task)


def test_project_many_equals_separate_projections():
    x, gates = th.randn(4, 5, 16), _gates(4, 8)
    for builder in (LinearBuilder(), LinearBuilder(Factorization(4, 4)), LinearBuilder(Factorization(4, 4, adapter_rank=2))):
        th.manual_seed(0)
        layers = [builder(16, 16) for _ in range(3)]
        with th.no_grad():
            for layer in layers:
                if getattr(layer, "adapter_rank", 0):
                    layer.adapter_up.normal_()  # a trained adapter: its term must be in both
        fused = project_many(layers, x, gates)
        for layer, out in zip(layers, fused):
            assert th.allclose(out, layer(x, gates), atol=1e-5)


def test_a_zero_adapter_changes_nothing_and_a_trained_one_adds_its_low_rank_term():
    """``adapter_rank``: with ``B = 0`` the layer (alone or fused by ``project_many``) computes bit for bit
    what the same factors compute without an adapter, so a transfer starts exactly at the student; once
    ``B`` is trained the layer adds ``x A^T B^T``, and its dense weight and pruned units include it (break:
    skip the adapter in ``forward`` -> the trained term is missing)."""
    th.manual_seed(0)
    weight, bias = th.randn(16, 16), th.randn(16)
    plain = [FactorizedLinear(16, 16, 4, 4, weight=weight, bias=bias) for _ in range(2)]
    adapted = [FactorizedLinear(16, 16, 4, 4, weight=weight, bias=bias, adapter_rank=3) for _ in range(2)]
    x, gates = th.randn(4, 5, 16), _gates(4, 8)
    with th.no_grad():
        assert th.equal(adapted[0](x, gates), plain[0](x, gates))
        for ours, theirs in zip(project_many(adapted, x, gates), project_many(plain, x, gates)):
            assert th.equal(ours, theirs)
        layer = adapted[0]
        layer.adapter_up.normal_()
        term = x @ (layer.adapter_up @ layer.adapter_down).T
        assert th.allclose(layer(x, gates), plain[0](x, gates) + term, atol=1e-5)
        assert th.allclose(layer.dense_weight(), plain[0].dense_weight() + layer.adapter_up @ layer.adapter_down, atol=1e-5)
        one = gates[0]
        U, s, V = layer.selected_units(one)
        assert th.allclose(x[0] @ ((U * s) @ V.T).T + bias, layer(x[:1], gates[:1])[0], atol=1e-5)


# -- gates ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [1, 3, 8])
def test_topk_gate_has_exactly_k_weights_summing_to_one(k):
    th.manual_seed(0)
    gate = TopKSoftGate(10, 8, k, hidden_dim=16)
    embedding = th.randn(32, 10, requires_grad=True)
    weights = gate(embedding)
    assert weights.shape == (32, 8)
    assert th.all((weights > 0).sum(-1) == k)
    assert th.all(weights >= 0)
    assert th.allclose(weights.sum(-1), th.ones(32), atol=1e-6)
    # the kept weights are the k largest scores
    scores = gate.score(embedding)
    assert th.equal(weights.topk(k, dim=-1).indices.sort(-1).values, scores.topk(k, dim=-1).indices.sort(-1).values)
    if k == 1:  # a top-1 weight is exactly 1 (hard routing in the forward pass) ...
        assert th.equal(weights.max(-1).values, th.ones(32))
    (weights * th.randn(32, 8)).sum().backward()
    # ... and straight-through in the backward pass: the task loss trains the gate for every k
    assert gate.score[0].weight.grad.abs().sum() > 0 and embedding.grad.abs().sum() > 0


def test_topk_gate_rejects_bad_k():
    with pytest.raises(ValueError):
        TopKSoftGate(4, 8, 9)


def test_morphology_encoder_ignores_padded_tokens():
    th.manual_seed(0)
    encoder = MorphologyEncoder(context_dim=6, max_tokens=5, embed_dim=8)
    context = th.randn(3, 5, 6)
    padding = th.tensor([[0, 0, 1, 1, 1], [0, 0, 0, 0, 1], [0, 0, 0, 0, 0]], dtype=th.bool)
    changed = context.clone()
    changed[padding] = th.randn(int(padding.sum()), 6) * 100
    for train in (True, False):
        encoder.train(train)
        assert th.allclose(encoder(context, padding), encoder(changed, padding), atol=1e-5)
    # control: a real token does change the embedding
    changed[0, 0] += 1.0
    assert not th.allclose(encoder(context, padding), encoder(changed, padding), atol=1e-3)


def test_router_deduplicates_without_changing_results():
    th.manual_seed(0)
    router = DiversionRouter(6, 5, 4, n_morph_tailors=6, n_task_tailors=4, top_k_morph=2, top_k_task=2, morph_embed_dim=8)
    robots = th.randn(3, 5, 6)
    tasks = th.randn(2, 4)
    index_r, index_t = th.arange(40) % 3, th.arange(40) % 2
    padding = th.zeros(40, 5, dtype=th.bool)
    padding[index_r == 1, 3:] = True
    batched = router(robots[index_r], padding, tasks[index_t])  # 40 >= dedup threshold
    for i in (0, 1, 2, 17):
        single = router(robots[index_r[i : i + 1]], padding[i : i + 1], tasks[index_t[i : i + 1]])
        assert th.allclose(batched.morphology[i], single.morphology[0], atol=1e-6)
        assert th.allclose(batched.task[i], single.task[0], atol=1e-6)


# -- Transformer ---------------------------------------------------------------------------------
@pytest.mark.parametrize("factorization", [None, Factorization(2, 2)])
def test_padded_tokens_never_affect_real_tokens(factorization):
    th.manual_seed(0)
    encoder = TransformerEncoder(16, n_layers=2, n_heads=2, ff_dim=32, builder=LinearBuilder(factorization))
    x = th.randn(3, 6, 16)
    padding = th.tensor([[0, 0, 0, 1, 1, 1], [0, 1, 1, 1, 1, 1], [0, 0, 0, 0, 0, 1]], dtype=th.bool)
    gates = _gates(3, 4) if factorization else None
    changed = x.clone()
    changed[padding] = th.randn(int(padding.sum()), 16) * 50
    for train in (True, False):
        encoder.train(train)
        with th.set_grad_enabled(train):
            a, b = encoder(x, padding, gates), encoder(changed, padding, gates)
        assert th.allclose(a[~padding], b[~padding], atol=1e-5)
    # control: a real token does change the other real tokens
    changed[0, 1] += th.randn(16)  # (a constant shift would vanish in the LayerNorm)
    assert not th.allclose(encoder(x, padding, gates)[0, 0], encoder(changed, padding, gates)[0, 0], atol=1e-4)


@pytest.mark.parametrize("collide", [False, True])
def test_router_deduplication_groups_exactly_the_identical_rows(monkeypatch, collide):
    from sb3_divmorph.nn import gates

    if collide:  # every row projects to 0: the check must catch it and fall back to the exact unique
        monkeypatch.setattr(gates, "_row_projection", lambda width, device: th.zeros(width, dtype=th.float64))
    rows = th.randn(7, 5)
    key = rows[th.randint(0, 7, (40,), generator=th.Generator().manual_seed(0))]
    key[3] = key[3] + 1e-7  # a near-duplicate is still a different robot
    first, inverse = gates._unique_rows(key)
    assert th.equal(key[first][inverse], key)
    expected = len(th.unique(key, dim=0))
    assert len(first) == expected
