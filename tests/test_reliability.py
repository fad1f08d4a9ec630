"""Reliability: a small morphology fuzz, property-based observation/mask invariants, determinism of
every task, and reproducibility of a short PPO run.

The long versions (1000-robot fuzz, 1M-step multi-task memory soak) are ``benchmarks/reliability.py``.
Bad-input handling (NaN / wrong-shape actions, a diverging simulation) and same-seed determinism of
FT over several robots are in ``test_env.py``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from conftest import unimal_xml
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import unimal_envs
from unimal_envs import contract as C
from unimal_envs.instructions import shipped_embeddings
from unimal_envs.morphology.generator import generate_unimal
from unimal_envs.morphology.loader import TORSO, load_morphology

FUZZ_SEEDS = range(7000, 7015)
#: Tasks of the property tests: plain locomotion, height map, goal, object.
PROPERTY_TASKS = ("FT", "VT", "PointNav", "ManipulateBox")
#: Huge finite values overflow the env's one-dot-product finiteness test (float32 actions): numpy
#: warns, then the env inspects the real slots and correctly accepts the action.
OVERFLOW_WARNING = "ignore:overflow encountered in matmul:RuntimeWarning"


def xml_counts(path: Path) -> tuple[int, int]:
    """``(tokens, hinges)`` counted in the MJCF text itself, independently of the loader: the bodies
    of the torso tree, and the motors (one per hinge in a UNIMAL file)."""
    root = ET.parse(path).getroot()
    torso = root.find(f".//body[@name='{TORSO}']")
    return 1 + len(torso.findall(".//body")), len(root.findall("./actuator/motor"))


def all_finite(obs: dict) -> bool:
    return all(np.isfinite(value).all() for value in obs.values())


def assert_obs_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


# ------------------------------------------------------------------------------------------ fuzz
@pytest.mark.parametrize("seed", FUZZ_SEEDS)
def test_generated_robot_compiles_and_runs_finite(seed, tmp_path):
    robot = generate_unimal(seed)
    path, _ = robot.write(tmp_path)
    morphology = load_morphology(path)
    assert morphology.num_limbs == robot.metadata["num_limbs"]
    assert morphology.dof == robot.metadata["dof"]
    env = gym.make("Unimal-FT-v0", morphologies=[path])
    obs, _ = env.reset(seed=seed)
    assert env.observation_space.contains(obs) and all_finite(obs)
    rng = np.random.default_rng(seed)
    for _ in range(50):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, C.ACTION_DIM).astype(np.float32))
        assert env.observation_space.contains(obs) and all_finite(obs)
        for key, space in env.observation_space.items():
            assert obs[key].shape == space.shape and obs[key].dtype == np.float32
        assert np.isfinite(reward)
        if terminated or truncated:
            obs, _ = env.reset()
            assert env.observation_space.contains(obs) and all_finite(obs)
    env.close()


# --------------------------------------------------------------------------- property-based tests
@pytest.fixture(scope="module")
def robot_pool(train_files, tmp_path_factory) -> list[tuple[Path, int, int]]:
    """Robots of the property tests with their token and hinge counts read from the file: two
    shipped train robots, two freshly generated ones and a hand-written one with "x" hinges only."""
    root = tmp_path_factory.mktemp("robots")
    paths = list(train_files[:2])
    paths += [generate_unimal(seed).write(root)[0] for seed in (FUZZ_SEEDS[0], FUZZ_SEEDS[1])]
    handmade = root / "three-x-legs.xml"
    handmade.write_text(unimal_xml(legs=3, hinges="x"))
    paths.append(handmade)
    return [(path, *xml_counts(path)) for path in paths]


_ENVS: dict[tuple, gym.Env] = {}


def env_for(task: str, path: Path, copy: int = 0, **kwargs) -> gym.Env:
    """A cached env (examples reset it with their own seed, so reuse does not couple them)."""
    key = (task, str(path), copy, tuple(sorted(kwargs.items())))
    if key not in _ENVS:
        _ENVS[key] = gym.make(unimal_envs.env_id(task), morphologies=[path], **kwargs)
    return _ENVS[key]


def teardown_module():
    for env in _ENVS.values():
        env.close()
    _ENVS.clear()


def action_sequences(max_steps: int, elements=st.floats(-1, 1, width=32)):
    """1 to ``max_steps`` float32 actions (in [-1, 1] by default)."""
    return st.integers(1, max_steps).flatmap(lambda n: arrays(np.float32, (n, C.ACTION_DIM), elements=elements))


def check_invariants(obs: dict, first: dict, task: str, tokens: int, hinges: int, space) -> None:
    assert space.contains(obs), {k: (v.dtype, v.shape) for k, v in obs.items() if not space[k].contains(v)}
    assert all_finite(obs)
    obs_mask, act_mask = obs["obs_padding_mask"], obs["act_padding_mask"]
    assert set(np.unique(obs_mask)) <= {0.0, 1.0} and set(np.unique(act_mask)) <= {0.0, 1.0}
    # Real tokens come first and their number is the robot's body count.
    assert obs_mask.tolist() == [0.0] * tokens + [1.0] * (C.MAX_TOKENS - tokens)
    padded = obs_mask == 1.0
    assert not obs["proprioceptive"][padded].any() and not obs["context"][padded].any()
    # One real action slot per hinge, none on padded tokens, and a slot is real exactly when its
    # hinge's static features (gear > 0) are in the observation.
    assert int((act_mask == 0).sum()) == hinges
    slots = act_mask.reshape(C.MAX_TOKENS, C.SLOTS_PER_TOKEN)
    assert (slots[padded] == 1.0).all()
    for slot, columns in enumerate(C.HINGE_SLOT_COLUMNS):
        gear = obs["proprioceptive"][:, columns][:, C.HINGE_STATIC][:, -1]
        np.testing.assert_array_equal(slots[:, slot] == 0.0, gear > 0)
    # Everything static stays put within the episode.
    for key in ("obs_padding_mask", "act_padding_mask", "context", "task_embedding", "task_index"):
        np.testing.assert_array_equal(obs[key], first[key], err_msg=key)
    assert obs["task_index"][0] == C.TASK_NAMES.index(task)
    np.testing.assert_array_equal(obs["task_embedding"], shipped_embeddings()[task])


@settings(max_examples=30, deadline=None)
@given(
    data=st.data(),
    seed=st.integers(0, 2**31 - 1),
    task=st.sampled_from(PROPERTY_TASKS),
    actions=action_sequences(20),
)
def test_observation_and_mask_invariants(robot_pool, data, seed, task, actions):
    path, tokens, hinges = data.draw(st.sampled_from(robot_pool), label="robot")
    env = env_for(task, path)
    first, _ = env.reset(seed=seed)
    check_invariants(first, first, task, tokens, hinges, env.observation_space)
    assert env.unwrapped.morphology.num_tokens == tokens and env.unwrapped.morphology.dof == hinges
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        check_invariants(obs, first, task, tokens, hinges, env.observation_space)
        assert np.isfinite(reward)
        if terminated or truncated:
            break


@pytest.mark.filterwarnings(OVERFLOW_WARNING)
@settings(max_examples=25, deadline=None)
@given(
    data=st.data(),
    seed=st.integers(0, 2**31 - 1),
    task=st.sampled_from(PROPERTY_TASKS),
    actions=action_sequences(12),
    noise=arrays(np.float32, (12, C.ACTION_DIM), elements=st.floats(width=32)),  # NaN and inf included
)
def test_padded_action_slots_have_no_effect(robot_pool, data, seed, task, actions, noise):
    path, _, _ = data.draw(st.sampled_from(robot_pool), label="robot")
    clean, noisy = env_for(task, path, copy=0), env_for(task, path, copy=1)
    obs_a, _ = clean.reset(seed=seed)
    obs_b, _ = noisy.reset(seed=seed)
    assert_obs_equal(obs_a, obs_b)
    padded = obs_a["act_padding_mask"] == 1.0
    for action, junk in zip(actions, noise):
        zeroed, filled = action.copy(), action.copy()
        zeroed[padded] = 0.0
        filled[padded] = junk[padded]
        obs_a, reward_a, term_a, trunc_a, _ = clean.step(zeroed)
        obs_b, reward_b, term_b, trunc_b, _ = noisy.step(filled)
        assert_obs_equal(obs_a, obs_b)
        assert (reward_a, term_a, trunc_a) == (reward_b, term_b, trunc_b)
        if term_a or trunc_a:
            break


@pytest.mark.filterwarnings(OVERFLOW_WARNING)
@settings(max_examples=25, deadline=None)
@given(
    data=st.data(),
    seed=st.integers(0, 2**31 - 1),
    task=st.sampled_from(("FT", "VT")),
    actions=action_sequences(10, st.floats(allow_nan=False, allow_infinity=False, width=32)),
)
def test_out_of_range_actions_act_like_clipped_ones(robot_pool, data, seed, task, actions):
    """Finite actions outside [-1, 1] (up to float32's largest) are clamped: observations, rewards
    (control cost included) and terminations equal those of the clipped action, all finite."""
    path, tokens, hinges = data.draw(st.sampled_from(robot_pool), label="robot")
    raw, clipped = (env_for(task, path, copy=c, ctrl_cost_weight=1e-3) for c in (0, 1))
    first, _ = raw.reset(seed=seed)
    clipped.reset(seed=seed)
    for action in actions:
        obs, reward, terminated, truncated, info = raw.step(action)
        expected = clipped.step(np.clip(action, -1.0, 1.0))
        check_invariants(obs, first, task, tokens, hinges, raw.observation_space)
        assert np.isfinite(reward) and np.isfinite(info["reward_ctrl"])
        assert_obs_equal(obs, expected[0])
        assert (reward, terminated, truncated) == expected[1:4]
        if terminated or truncated:
            break


# ----------------------------------------------------------------------------------- determinism
def _trace(env: gym.Env, seed: int, actions: np.ndarray) -> list:
    obs, info = env.reset(seed=seed)
    trace = [info["morphology"], obs]
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        trace += [obs, reward, terminated, truncated]
        if terminated or truncated:
            obs, _ = env.reset()  # unseeded: continues the seeded generator
            trace.append(obs)
    return trace


def _assert_same_trace(a: list, b: list) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        if isinstance(x, dict):
            assert_obs_equal(x, y)
        else:
            assert x == y


@pytest.mark.parametrize("task", C.TASK_NAMES)
def test_every_task_is_deterministic_given_seed_and_actions(task, train_files):
    """Same seed + same actions -> identical observations, rewards and episode ends, on a fresh env
    and on a used one (a previous episode on the cached world must leave no trace)."""
    actions = np.random.default_rng(3).uniform(-1, 1, (30, C.ACTION_DIM)).astype(np.float32)
    make = lambda: gym.make(unimal_envs.env_id(task), morphologies=[train_files[0]])  # noqa: E731
    reference = _trace(make(), 11, actions)
    _assert_same_trace(reference, _trace(make(), 11, actions))
    used = make()
    _trace(used, 12, actions[::-1])
    _assert_same_trace(reference, _trace(used, 11, actions))
    other = _trace(make(), 12, actions)
    assert not np.array_equal(reference[1]["proprioceptive"], other[1]["proprioceptive"])


def test_ppo_training_is_reproducible(train_files):
    """Two single-process PPO runs with the same seed end with bit-identical parameters."""
    import torch as th
    from stable_baselines3 import PPO

    import sb3_divmorph  # noqa: F401  (registers the "MetaMorphPolicy" alias)

    def model():
        env = gym.make("Unimal-FT-v0", morphologies=[train_files[0]])
        return PPO(
            "MetaMorphPolicy", env, seed=0, n_steps=64, batch_size=64, n_epochs=1, device="cpu",
            policy_kwargs=dict(preset="small", d_model=16, n_layers=1, ff_dim=32, exteroception={}),
        )  # fmt: skip

    def params(ppo) -> dict[str, th.Tensor]:
        return {name: value.detach().clone() for name, value in ppo.policy.state_dict().items()}

    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        initial = params(model())
        runs = []
        for _ in range(2):
            ppo = model()
            ppo.learn(128)
            assert ppo.num_timesteps == 128
            runs.append(params(ppo))
    finally:
        th.set_num_threads(threads)
    assert runs[0].keys() == runs[1].keys() == initial.keys()
    for name in runs[0]:
        assert th.equal(runs[0][name], runs[1][name]), f"{name} differs between the two runs"
    assert any(not th.equal(runs[0][name], initial[name]) for name in initial), "training changed nothing"
