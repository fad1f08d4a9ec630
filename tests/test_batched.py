"""The batched backend (MuJoCo Warp, run here on CPU Warp): agreement with the single env, every
task and MultiTask stepping with auto-resets, physics faults kept to their world, PPO on it, and
clear errors for bad input.

Tolerances were measured on this machine (float32 Warp against float64 MuJoCo, random actions,
the shipped robots): after the first control step observations agree to ~2e-6 and rewards to
~1e-4; after ten steps to ~1e-5 and ~3e-4. Beyond a few dozen steps the two diverge as contacts
amplify float32 rounding (chaos, not a bug), so the tests stop at ten.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp", reason="the batched backend needs the mujoco-warp extra")

from batched_mirror import mirror_world  # noqa: E402

import unimal_envs  # noqa: E402,F401
from unimal_envs import contract as C  # noqa: E402
from unimal_envs.batched import make_batched_env  # noqa: E402
from unimal_envs.morphology.loader import MorphologyError, load_morphologies, morphology_files  # noqa: E402

ROBOTS = morphology_files("train")[:2]
#: Agreement after the first control step, and after ten (observation max |diff|, reward |diff|).
FIRST_STEP_OBS, FIRST_STEP_REWARD = 2e-5, 1e-3
TEN_STEPS_OBS, TEN_STEPS_REWARD = 2e-3, 2e-2


def _step_world(benv, world: int, action: np.ndarray):
    actions = torch.zeros(benv.num_envs, C.ACTION_DIM)
    actions[world] = torch.as_tensor(action)
    return benv.step_tensors(actions)


@pytest.mark.parametrize(
    "task", ["FT", "VT", "Patrol", "Escape", "ManipulateBox", "Obstacle", "PointNav", "Exploration", "Incline", "PushBoxIncline"]
)
def test_a_world_agrees_with_the_single_env_from_the_same_state_with_the_same_actions(task):
    benv = make_batched_env(task, morphologies=ROBOTS, worlds_per_robot=2, device="cpu", seed=0, terrain_variants=2)
    benv.reset()
    for robot in range(2):
        env = gym.make(unimal_envs.env_id(task), morphologies=ROBOTS).unwrapped
        single_obs, _ = env.reset(seed=robot, options={"morphology": robot})
        world = 2 * robot + 1
        batched_obs = mirror_world(benv, world, env)
        for key in C.observation_space().spaces:
            np.testing.assert_allclose(batched_obs[key][world].numpy(), single_obs[key], atol=1e-5, err_msg=key)
        rng = np.random.default_rng(robot)
        for t in range(10):
            action = rng.uniform(-1, 1, C.ACTION_DIM).astype(np.float32)
            single_obs, reward, terminated, _, info = env.step(action)
            _, batched_reward, batched_terminated, _, batched_info = _step_world(benv, world, action)
            final = batched_info["final_observation"]
            obs_tol, reward_tol = (FIRST_STEP_OBS, FIRST_STEP_REWARD) if t == 0 else (TEN_STEPS_OBS, TEN_STEPS_REWARD)
            for key in C.observation_space().spaces:
                np.testing.assert_allclose(final[key][world].numpy(), single_obs[key], atol=obs_tol, err_msg=f"{key} step {t}")
            assert abs(float(batched_reward[world]) - reward) <= reward_tol, (t, reward, float(batched_reward[world]))
            for term in (k for k in info if k.startswith("reward_")):
                assert abs(float(batched_info[term][world]) - info[term]) <= reward_tol, (t, term)
            assert bool(batched_terminated[world]) == terminated
            if terminated:
                break


@pytest.mark.parametrize("task", [*C.TASK_NAMES, "MultiTask"])
def test_every_task_steps_with_finite_values_and_resets_each_world_on_its_own(task):
    benv = make_batched_env(
        task,
        morphologies=ROBOTS,
        worlds_per_robot=4,
        device="cpu",
        seed=1,
        max_episode_steps=20,
        terrain_variants=2,
        tasks=["FT", "Patrol"] if task == "MultiTask" else None,
    )
    n = benv.num_envs
    assert n == 2 * 4 * (2 if task == "MultiTask" else 1)
    obs = benv.reset()
    assert set(obs) == set(C.observation_space().spaces)
    assert all(obs[k].shape == (n, *space.shape) and obs[k].dtype == np.float32 for k, space in C.observation_space().spaces.items())
    rng = np.random.default_rng(0)
    episode_steps = np.zeros(n, dtype=int)
    ended = 0
    for _ in range(50):
        obs, reward, done, infos = benv.step(rng.uniform(-1, 1, (n, C.ACTION_DIM)).astype(np.float32))
        episode_steps += 1
        assert all(np.isfinite(v).all() for v in obs.values()) and np.isfinite(reward).all()
        for i in np.flatnonzero(done):
            info = infos[i]
            assert info["TimeLimit.truncated"] == (episode_steps[i] == 20 and "termination" not in info)
            assert episode_steps[i] <= 20
            assert set(info["terminal_observation"]) == set(obs)
            ended += 1
        episode_steps[done] = 0
    assert ended >= n, "every world is truncated at 20 steps, so 50 steps end at least one episode each"
    assert [info["task"] for info in infos[::8]] == (["FT", "Patrol"] if task == "MultiTask" else [task] * (n // 8))
    # Each world's static observations are its own robot's and task's.
    np.testing.assert_array_equal(obs["task_index"][:, 0], [C.TASK_NAMES.index(t) for t in benv.task_names])
    robots = {m.name: m for m in load_morphologies(ROBOTS)}
    for i in range(n):
        np.testing.assert_array_equal(obs["context"][i], robots[benv.morphology_names[i]].context)


def test_a_reset_world_is_back_at_the_spawn_pose_and_the_others_go_on():
    benv = make_batched_env("FT", morphologies=ROBOTS[:1], worlds_per_robot=3, device="cpu", seed=0, max_episode_steps=1000)
    benv.reset_tensors()
    block = benv.blocks[0]
    spawn = block.groups[0].qpos0[:3].clone()
    for _ in range(15):
        benv.step_tensors(torch.full((3, C.ACTION_DIM), 0.8))
    moved = block.read().torso.clone()
    assert (moved - spawn).norm(dim=1).min() > 0.05
    block.reset(torch.tensor([False, True, False]), benv.reset_noise_scale)
    after = block.read().torso
    assert torch.allclose(after[1], spawn, atol=0.01)
    assert torch.equal(after[[0, 2]], moved[[0, 2]])


def test_each_world_draws_its_own_episode_from_the_single_envs_distributions():
    box = make_batched_env("ManipulateBox", morphologies=ROBOTS[:1], worlds_per_robot=16, device="cpu", seed=0)
    box.reset_tensors()
    block, group = box.blocks[0], box.blocks[0].groups[0]
    placed = group.qpos[:, group.box_qpos : group.box_qpos + 3]
    goal = block.task.goal
    assert ((placed[:, 0] >= 15) & (placed[:, 0] <= 24)).all() and (placed[:, 1].abs() <= 9.8).all()
    assert torch.allclose(placed[:, 1] * 10, torch.round(placed[:, 1] * 10), atol=1e-4)  # DERL's 0.1 m grid
    assert ((goal[:, 0] - placed[:, 0] >= 15) | (goal[:, 0] == 50.5)).all() and (goal[:, 1].abs() <= 9.5).all()
    assert len({tuple(p.tolist()) for p in placed}) > 8, "worlds draw their own boxes"
    robot = group.qpos[:, group.robot_qpos] - group.qpos0[group.robot_qpos]
    assert (robot.abs() <= 0.005 + 1e-6).all() and (robot.abs() > 0).any()  # reset noise U(-0.005, 0.005)

    nav = make_batched_env("PointNav", morphologies=ROBOTS[:1], worlds_per_robot=16, device="cpu", seed=0)
    nav.reset_tensors()
    goal = nav.blocks[0].task.goal
    assert ((goal[:, 0] >= -43.5) & (goal[:, 0] < 43) & (goal[:, 1].abs() <= 39.5)).all() and goal[:, 0].unique().numel() == 16

    for task in ("VT", "Obstacle"):
        env = make_batched_env(task, morphologies=ROBOTS[:1], worlds_per_robot=16, device="cpu", seed=0, terrain_variants=4)
        env.reset_tensors()
        block, group = env.blocks[0], env.blocks[0].groups[0]
        variant = block.variant
        assert variant.unique().numel() > 1, "worlds stand on different terrain variants"
        if task == "VT":  # each world's terrain geom reads its variant's height field
            assert torch.equal(group.geom_dataid[:, group.terrain_geom].long(), torch.as_tensor(group.variant_dataid)[variant])
        else:  # each world's blocks are its variant's layout
            assert torch.equal(group.mocap_pos[:, torch.as_tensor(group.obstacle_mocap)], block.layout[variant][..., :3])
            assert torch.equal(group.geom_size[:, torch.as_tensor(group.obstacle_ids)], block.layout[variant][..., 3:])


def test_a_physics_fault_ends_only_its_own_world():
    twins = [make_batched_env("FT", morphologies=ROBOTS, worlds_per_robot=2, device="cpu", seed=3) for _ in range(2)]
    for env in twins:
        env.reset_tensors()
    twins[1].blocks[0].groups[0].qvel[1, 0] = float("nan")  # world 1 blows up
    actions = torch.full((4, C.ACTION_DIM), 0.3)
    (obs_a, reward_a, term_a, _, info_a), (obs_b, reward_b, term_b, _, info_b) = (env.step_tensors(actions) for env in twins)
    assert info_b["physics_fault"].tolist() == [False, True, False, False]
    assert bool(term_b[1]) and float(reward_b[1]) == 0.0
    others = [0, 2, 3]
    assert torch.equal(reward_a[others], reward_b[others])
    assert torch.equal(obs_a["proprioceptive"][others], obs_b["proprioceptive"][others])
    assert torch.isfinite(obs_b["proprioceptive"]).all(), "the faulted world was reset"
    twins[1].step_async(np.zeros((4, C.ACTION_DIM), dtype=np.float32))
    twins[1].blocks[0].groups[1].qpos[0, 2] = float("inf")
    _, _, dones, infos = twins[1].step_wait()
    assert dones[2] and infos[2]["physics_fault"] and infos[2]["termination"] == "physics_fault"
    assert np.isfinite(infos[2]["terminal_observation"]["proprioceptive"]).all()


def test_ppo_trains_saves_and_loads_on_the_batched_env(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    import sb3_divmorph  # noqa: F401  (registers the policy aliases)

    tiny = dict(d_model=16, n_layers=1, ff_dim=32, exteroception=dict(hfield=[8], goal=[4], object=[4]))
    venv = VecNormalize(
        VecMonitor(
            make_batched_env("VT", morphologies=ROBOTS, worlds_per_robot=4, device="cpu", seed=0, max_episode_steps=16, terrain_variants=2)
        ),
        norm_obs_keys=["proprioceptive", "hfield"],
    )
    model = PPO(
        "DivMorphPolicy",
        venv,
        n_steps=16,
        batch_size=64,
        n_epochs=1,
        seed=0,
        policy_kwargs=dict(tiny, n_morph_tailors=4, n_task_tailors=4, top_k_morph=2, top_k_task=2),
    )
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=2 * 16 * 8)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    assert len(model.ep_info_buffer) >= 8, "16-step episodes were monitored"
    model.save(tmp_path / "ppo")
    loaded = PPO.load(tmp_path / "ppo", env=venv)
    obs = venv.reset()
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0], atol=1e-6)


def test_the_batched_evaluation_plays_each_robots_episodes_as_the_single_env_evaluation_does():
    """``batched_returns``: one world per episode, each counted to its own first end, with the
    model's frozen statistics and clipped mean action -- per robot the returns of the single-env
    evaluation (episodes differ only by the 0.005 reset noise over 20 steps), every episode once,
    the same rows again on a second call (break: feed raw observations -> the returns leave the
    single env's)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    import sb3_divmorph  # noqa: F401  (registers the policy aliases)
    from divmorph.pipeline.batched_evaluation import batched_returns, make_evaluation_env
    from divmorph.pipeline.curves import robot_venv, rollout_returns

    steps, episodes = 20, 3
    train = VecNormalize(robot_venv("Unimal-FT-v0", ROBOTS, steps, 0), norm_obs_keys=["proprioceptive"], norm_reward=False)
    model = PPO("MetaMorphPolicy", train, seed=0, policy_kwargs=dict(d_model=16, n_layers=1, ff_dim=32))
    train.reset()
    for _ in range(30):  # statistics that differ from raw observations
        train.step(np.stack([train.action_space.sample() for _ in ROBOTS]))
    train.training = False
    single = rollout_returns(model, robot_venv("Unimal-FT-v0", ROBOTS, steps, 0), ROBOTS, episodes, train.normalize_obs)
    env = make_evaluation_env("Unimal-FT-v0", ROBOTS, episodes, steps, 0, "cpu", 2)
    batched = batched_returns(model, env, train, seed=0)
    assert sorted((r["robot"], r["episode"]) for r in batched) == sorted((p.stem, e) for p in ROBOTS for e in range(episodes))
    assert all(r["length"] == steps for r in batched)
    for robot in ROBOTS:
        ours = np.mean([r["return"] for r in batched if r["robot"] == robot.stem])
        theirs = np.mean([r["return"] for r in single if r["robot"] == robot.stem])
        assert ours == pytest.approx(theirs, rel=0.05, abs=0.05), robot.stem
    assert batched_returns(model, env, train, seed=0) == batched


def test_the_batched_evaluation_counts_each_world_to_its_own_first_end():
    """Worlds end at different steps (world i after i + 2) and go on after their auto-reset: each
    return and length is its first episode's alone (break: drop the ``running`` mask -> the early
    worlds are credited with the steps the others still take)."""
    from types import SimpleNamespace

    from gymnasium import spaces

    from divmorph.pipeline.batched_evaluation import batched_returns

    class Worlds:  # the slice of BatchedUnimalEnv's torch interface the evaluation uses
        num_envs, worlds_per_robot, torch_device = 4, 2, torch.device("cpu")
        morphology_names = ["a", "a", "b", "b"]

        def seed(self, seed):
            self.t = 0

        def reset_tensors(self):
            return {"x": torch.zeros(4, 1)}

        def step_tensors(self, actions):
            self.t += 1
            ended = torch.arange(4) + 2 == self.t
            return {"x": torch.zeros(4, 1)}, torch.ones(4), ended, torch.zeros(4, dtype=torch.bool), {}

    policy = SimpleNamespace(training=False, device=torch.device("cpu"), set_training_mode=lambda mode: None)
    policy._predict = lambda obs, deterministic: torch.zeros(4, C.ACTION_DIM)
    model = SimpleNamespace(policy=policy, action_space=spaces.Box(-1, 1, (C.ACTION_DIM,)))
    rows = batched_returns(model, Worlds(), None, seed=0)
    assert [(r["robot"], r["episode"], r["return"], r["length"]) for r in rows] == [
        ("a", 0, 2.0, 2),
        ("a", 1, 3.0, 3),
        ("b", 0, 4.0, 4),
        ("b", 1, 5.0, 5),
    ]


def test_bad_input_is_refused_with_a_message_that_names_the_problem(write_robot):
    from conftest import unimal_xml

    with pytest.raises(ValueError, match="device 'cuda:7' does not exist here; available Warp devices"):
        make_batched_env("FT", morphologies=ROBOTS, worlds_per_robot=2, device="cuda:7")
    with pytest.raises(ValueError, match=r"need about .* GiB on cpu .* lower worlds_per_robot to at most"):
        make_batched_env("FT", morphologies=ROBOTS, worlds_per_robot=10**8, device="cpu")
    with pytest.raises(ValueError, match="worlds_per_robot must be at least 1"):
        make_batched_env("FT", morphologies=ROBOTS, worlds_per_robot=0, device="cpu")
    with pytest.raises(ValueError, match="terrain_variants must be at least 1"):
        make_batched_env("VT", morphologies=ROBOTS, worlds_per_robot=1, device="cpu", terrain_variants=0)
    pgs = write_robot(unimal_xml().replace('<option timestep="0.005"/>', '<option timestep="0.005" solver="PGS"/>'), "pgs_robot")
    with pytest.raises(MorphologyError, match="pgs_robot: MuJoCo Warp cannot simulate this robot's world: mjSOL_PGS"):
        make_batched_env("FT", morphologies=[pgs], worlds_per_robot=2, device="cpu")
    env = make_batched_env("FT", morphologies=ROBOTS[:1], worlds_per_robot=2, device="cpu")
    env.reset()
    with pytest.raises(ValueError, match=r"actions have shape \(3, 24\); this env takes \(2, 24\)"):
        env.step_tensors(torch.zeros(3, C.ACTION_DIM))
    with pytest.raises(NotImplementedError, match="robot sampling .* does not apply"):
        env.env_method("set_morphology_probabilities", None)


def test_a_custom_instruction_is_what_the_worlds_observe():
    from unimal_envs.instructions import embed_instruction

    words = "Walk to the red tile and stay on it."
    env = make_batched_env("PointNav", morphologies=ROBOTS[:1], worlds_per_robot=2, device="cpu", instruction=words, text_encoder="hash")
    np.testing.assert_array_equal(env.reset()["task_embedding"], np.stack([embed_instruction(words, "hash")] * 2))
    with pytest.raises(ValueError, match="MultiTask uses each task's own instruction"):
        make_batched_env("MultiTask", morphologies=ROBOTS[:1], worlds_per_robot=1, device="cpu", instruction=words)


@pytest.mark.parametrize("task", ["Incline", "VT", "Escape"])
def test_heights_measured_from_the_ground_are_the_single_envs(task):
    """``height_reference="ground"``: a world moved off the spawn point, onto the incline's slope or
    the terrain, observes the token heights the single env observes in the same state -- measured
    from the ground under the torso, not from z = 0 (break: skip the subtraction in the block's
    ``observe`` -> the heights differ by the ground's)."""
    import mujoco

    benv = make_batched_env(
        task, morphologies=ROBOTS[:1], worlds_per_robot=2, device="cpu", seed=0, terrain_variants=2, height_reference="ground"
    )
    assert benv.get_attr("height_reference") == ["ground", "ground"]
    benv.reset()
    env = gym.make(unimal_envs.env_id(task), morphologies=ROBOTS[:1], height_reference="ground").unwrapped
    env.reset(seed=0)
    if task == "Incline":
        env.data.qpos[:2] += (6.0, 1.0)  # up the slope
    else:  # onto the terrain's highest sample
        grid = env.arena.grid
        row, col = np.unravel_index(np.abs(grid.heights).argmax(), grid.heights.shape)
        env.data.qpos[:2] = (grid.x0 + col * grid.resolution, grid.y0 + row * grid.resolution)
    mujoco.mj_forward(env.model, env.data)
    single = env._observation()
    ground = env.arena.ground_height(*env.data.qpos[:2])
    assert abs(ground) > 0.05, "the test needs a place where the ground is not at z = 0"
    batched = mirror_world(benv, 1, env)
    np.testing.assert_allclose(batched["proprioceptive"][1].numpy(), single["proprioceptive"], atol=1e-5)


def test_without_mujoco_warp_the_message_names_the_extra(monkeypatch):
    import unimal_envs.batched as batched

    monkeypatch.setattr(batched, "_MISSING", ImportError("No module named 'mujoco_warp'"))
    with pytest.raises(ImportError, match=r'pip install "divmorph\[warp\]"'):
        batched.make_batched_env("FT")


def test_the_pipeline_trains_its_stages_on_the_batched_backend_when_the_profile_says_so(tmp_path, monkeypatch):
    import json

    from test_pipeline import write_profiles

    import unimal_envs.batched as batched
    from divmorph.cli import main as cli

    built = []
    original = batched.make_batched_env

    def counting(task, **kwargs):
        built.append((task, kwargs["worlds_per_robot"], kwargs["device"], kwargs["terrain_variants"]))
        return original(task, **kwargs)

    monkeypatch.setattr(batched, "make_batched_env", counting)
    from sb3_divmorph.algos.device_ppo import DevicePPO

    on_device, collect = [], DevicePPO._collect_on_device
    monkeypatch.setattr(DevicePPO, "_collect_on_device", lambda self, *a: on_device.append(1) or collect(self, *a))
    on_warp = {"env_backend": "batched", "worlds_per_robot": 2, "terrain_variants": 3}
    profiles = write_profiles(
        tmp_path,
        teachers__n_timesteps=64,
        teachers__overrides={"n_steps": 16, "batch_size": 32, "n_epochs": 1},
        **{f"{stage}__{key}": value for stage in ("teachers", "distill", "transfer") for key, value in on_warp.items()},
        transfer__tasks=["PointNav"],
        transfer__arms=["divmorph"],
        transfer__eval_every=32,
        transfer__eval_episodes=2,
        transfer__eval_robots=1,
        transfer__eval_backend="batched",
        transfer__overrides={"n_steps": 16, "batch_size": 32, "n_epochs": 1},
        transfer__n_timesteps=64,
        distill__n_steps=16,
        distill__n_timesteps=64,
    )
    out = tmp_path / "run"
    for stage in ("teachers", "distill", "transfer"):
        assert cli([stage, "--profile", "tiny", "--profiles", str(profiles), "--out", str(out), "--no-progress"]) == 0
    # the transfer run's curves too: one env per robot split, a world per episode (transfer.eval_backend: batched)
    assert [task for task, _, _, _ in built] == ["FT", "Patrol", "MultiTask", "PointNav", "PointNav", "PointNav"]
    assert len(on_device) >= 2, "each teacher's rollouts stayed on the device (DevicePPO)"
    assert all(worlds == 2 and device == "cpu" and variants == 3 for _, worlds, device, variants in built)
    assert (out / "transfer" / "PointNav" / "divmorph" / "seed-0" / "model.zip").is_file()
    from divmorph.pipeline.curves import read_eval

    rows = read_eval(out / "transfer" / "PointNav" / "divmorph" / "seed-0" / "eval.csv")
    for step in (0, 32, 64):
        assert sorted((r["split"], r["episode"]) for r in rows if r["timesteps"] == step) == [
            ("novel", 0),
            ("novel", 1),
            ("train", 0),
            ("train", 1),
        ]
    # the evaluation stage plays the run's model again in the single env rather than reuse a batched curve point
    import pandas as pd

    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.evaluate import evaluate

    folder = evaluate(load_profile("tiny", profiles), out, models=["transfer-divmorph"], progress_bar=False, into=tmp_path / "evaluation")
    table = pd.read_csv(folder / "returns.csv")
    played = table[(table.model == "transfer-divmorph") & (table.split == "train")].sort_values("episode")["return"].to_numpy()
    curve = [r["return"] for r in sorted(rows, key=lambda r: r["episode"]) if r["timesteps"] == 64 and r["split"] == "train"]
    assert len(played) == 2 and not np.allclose(played, curve)
    recorded = json.loads((out / "run.json").read_text())["configuration"]
    assert recorded["teachers"]["env_backend"] == recorded["distill"]["env_backend"] == "batched"


def test_goal_range_bounds_the_goal_as_the_single_env_does():
    """``goal_range``: a world's bounded goal and object positions are the single env's in the same
    state (break: drop the bound from the block's ``observe`` -> the world reads the raw ~30 m goal)."""
    benv = make_batched_env("ManipulateBox", morphologies=ROBOTS[:1], worlds_per_robot=2, device="cpu", seed=0, goal_range=4.0)
    assert benv.get_attr("goal_range") == [4.0, 4.0]
    benv.reset()
    env = gym.make("Unimal-ManipulateBox-v0", morphologies=ROBOTS[:1], goal_range=4.0).unwrapped
    env.reset(seed=0)
    single = env._observation()
    batched = mirror_world(benv, 1, env)
    assert np.linalg.norm(single["goal"]) == pytest.approx(4.0, rel=1e-5)
    np.testing.assert_allclose(batched["goal"][1].numpy(), single["goal"], atol=1e-4)
    np.testing.assert_allclose(batched["object"][1].numpy(), single["object"], atol=1e-4)
