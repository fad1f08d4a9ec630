"""``UnimalVecEnv`` gives the trajectories of ``VecMonitor(DummyVecEnv([gym.make(...)]))``, resets included."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

import unimal_envs
from unimal_envs.vector import UnimalVecEnv, make_unimal_vec_env


def sb3_stack(env_id, robots, n_envs, max_steps, seed):
    venv = VecMonitor(DummyVecEnv([lambda: gym.make(env_id, morphologies=robots, max_episode_steps=max_steps) for _ in range(n_envs)]))
    venv.seed(seed)
    return venv


@pytest.mark.parametrize("task", ["FT", "Escape"])
def test_the_same_trajectories_as_sb3s_stack(train_files, task):
    """Observations (every key), rewards, dones and the infos SB3 reads (time-limit flag, terminal observation,
    episode return and length) equal at every step over several episodes of each env, through time limits and
    terminations, with the robot drawn afresh at each reset (broken once: the time limit counted from 0 -> fails)."""
    env_id, robots, n_envs, max_steps = unimal_envs.env_id(task), train_files[:3], 3, 25
    reference = sb3_stack(env_id, robots, n_envs, max_steps, seed=5)
    lean = make_unimal_vec_env(env_id, n_envs, seed=5, max_episode_steps=max_steps, morphologies=robots)
    obs_a, obs_b = reference.reset(), lean.reset()
    rng = np.random.default_rng(0)
    finished = {"time limit": 0, "termination": 0}
    for step in range(120):
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key], err_msg=f"{key} at step {step}")
            assert obs_a[key].dtype == obs_b[key].dtype
        actions = rng.uniform(-3, 3, (n_envs, *reference.action_space.shape)).astype(np.float32)
        obs_a, reward_a, done_a, infos_a = reference.step(actions)
        obs_b, reward_b, done_b, infos_b = lean.step(actions)
        np.testing.assert_array_equal(reward_a, reward_b)
        np.testing.assert_array_equal(done_a, done_b)
        for info_a, info_b in zip(infos_a, infos_b):
            assert info_a["TimeLimit.truncated"] == info_b["TimeLimit.truncated"]
            assert ("episode" in info_a) == ("episode" in info_b)
            if "episode" in info_a:
                assert (info_a["episode"]["r"], info_a["episode"]["l"]) == (info_b["episode"]["r"], info_b["episode"]["l"])
                for key, value in info_a["terminal_observation"].items():
                    np.testing.assert_array_equal(value, info_b["terminal_observation"][key])
                finished["time limit" if info_a["TimeLimit.truncated"] else "termination"] += 1
    assert finished["time limit"] >= n_envs  # the comparison went through resets of both kinds
    if task == "FT":
        assert finished["termination"] > 0  # flailing at 3x the action range topples some robot


def test_fresh_arrays_each_step(train_files):
    """A step's observations are new arrays: what a caller (VecNormalize, a buffer) keeps is not overwritten by the
    next step (broken once: one set of buffers reused -> fails)."""
    venv = make_unimal_vec_env(unimal_envs.env_id("FT"), 2, seed=0, max_episode_steps=50, morphologies=train_files[:2])
    venv.reset()
    actions = np.full((2, *venv.action_space.shape), 0.5, dtype=np.float32)
    first = venv.step(actions)[0]
    kept = {key: value.copy() for key, value in first.items()}
    venv.step(-actions)
    for key in kept:
        np.testing.assert_array_equal(first[key], kept[key])


def test_the_vec_env_api(train_files):
    """Methods and attributes reach every env; evaluate_policy reads its episodes as a monitored env's; a factory
    returning one env twice is refused."""
    robots = train_files[:2]
    venv = make_unimal_vec_env(unimal_envs.env_id("FT"), 2, seed=0, max_episode_steps=10, morphologies=robots)
    assert venv.get_attr("morphology_names") == [[r.stem for r in robots]] * 2
    venv.env_method("set_morphology_probabilities", np.array([1.0, 0.0]))
    venv.reset()
    assert [m.name for m in venv.get_attr("morphology")] == [robots[0].stem] * 2

    class Zero:
        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            return np.zeros((len(obs["proprioceptive"]), *venv.action_space.shape), dtype=np.float32), None

    with __import__("warnings").catch_warnings():
        __import__("warnings").simplefilter("error")  # SB3 warns when the env is not monitored
        returns, lengths = evaluate_policy(Zero(), venv, n_eval_episodes=2, return_episode_rewards=True)
    assert lengths == [10, 10]
    env = gym.make(unimal_envs.env_id("FT"), morphologies=robots).unwrapped
    with pytest.raises(ValueError, match="same env"):
        UnimalVecEnv([lambda: env, lambda: env])


def test_rl_zoo_runs_the_shipped_entries_through_it(train_files, tmp_path):
    """rl-zoo builds a DummyVecEnv of Monitor-wrapped envs (SB3's make_vec_env with a monitor folder) and applies the
    entries' ``vec_env_wrapper``: the wrapped env is a UnimalVecEnv with the DummyVecEnv's trajectories, and the
    Monitors still write rl-zoo's logs (broken once: the seeds not carried over -> the first observations differ)."""
    from rl_zoo3.utils import get_wrapper_class
    from stable_baselines3.common.env_util import make_vec_env

    import sb3_divmorph.zoo as zoo

    entry = zoo.hyperparams["Unimal-Escape-v0"]
    assert entry["vec_env_wrapper"] == zoo.LEAN_VEC_ENV
    zoo.zoo_hyperparams("Unimal-Escape-v0")  # the pipeline reads the same entry (its envs are UnimalVecEnvs already)

    def zoo_venv(folder):
        kwargs = dict(morphologies=train_files[:2], max_episode_steps=15)
        return make_vec_env(unimal_envs.env_id("Escape"), n_envs=2, seed=1, env_kwargs=kwargs, monitor_dir=str(folder))

    reference = zoo_venv(tmp_path / "dummy")
    lean = get_wrapper_class(entry, "vec_env_wrapper")(zoo_venv(tmp_path / "lean"))
    assert isinstance(lean, UnimalVecEnv)
    obs_a, obs_b = reference.reset(), lean.reset()
    rng = np.random.default_rng(1)
    for _ in range(40):
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key], err_msg=key)
        actions = rng.uniform(-1, 1, (2, *reference.action_space.shape)).astype(np.float32)
        obs_a, reward_a, done_a, _ = reference.step(actions)
        obs_b, reward_b, done_b, _ = lean.step(actions)
        np.testing.assert_array_equal(reward_a, reward_b)
        np.testing.assert_array_equal(done_a, done_b)
    lean.close()
    rows = [line for path in (tmp_path / "lean").glob("*.monitor.csv") for line in path.read_text().splitlines()[2:]]
    assert len(rows) >= 4  # 40 steps of 15-step episodes, two envs
