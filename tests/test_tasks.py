"""The ten tasks and Unimal-MultiTask-v1: rewards, terminations, height maps, goal/object frames."""

from __future__ import annotations

import math

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import unimal_envs
from unimal_envs import contract as C
from unimal_envs.arenas.heightfield import FORWARD_CELLS, LATERAL_CELLS
from unimal_envs.tasks import TASKS

ZERO = np.zeros(C.ACTION_DIM, np.float32)
ALL_IDS = [unimal_envs.env_id(t) for t in TASKS] + ["Unimal-MultiTask-v1"]


def make(task: str, files, **kwargs) -> gym.Env:
    env = gym.make(unimal_envs.env_id(task), morphologies=files, **kwargs)
    env.reset(seed=0)
    return env


def push(env: gym.Env, direction, steps: int = 15) -> float:
    """Drag the torso horizontally with a force of about its robot's weight; return the reward sum."""
    u = env.unwrapped
    weight = float(u.model.body_subtreemass[u.robot.torso_id]) * 9.81
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    total = 0.0
    for _ in range(steps):
        u.data.xfrc_applied[u.robot.torso_id, :2] = 1.5 * weight * direction
        _, reward, terminated, _, _ = env.step(ZERO)
        total += reward
        if terminated:
            break
    return total


def toward_goal(env) -> np.ndarray:
    u = env.unwrapped
    return u.task.goal[:2] - u.robot.torso_qpos[:2]


def toward_box(env) -> np.ndarray:
    u = env.unwrapped
    return u.data.xpos[u.task._box, :2] - u.robot.torso_qpos[:2]


@pytest.mark.parametrize(
    "task, direction",
    [
        ("FT", lambda env: (1, 0)),
        ("VT", lambda env: (1, 0)),
        ("Incline", lambda env: (1, 0)),
        ("Obstacle", lambda env: (1, 0)),
        ("Patrol", toward_goal),
        ("PointNav", toward_goal),
        ("PushBoxIncline", toward_box),
        ("ManipulateBox", toward_box),
    ],
)
def test_moving_toward_the_objective_is_rewarded_and_away_is_penalised(train_files, task, direction):
    env = make(task, train_files[:1])
    assert push(env, direction(env)) > 1.0
    env.reset(seed=0)
    assert push(env, -np.asarray(direction(env), float)) < -1.0


def test_escape_rewards_radial_progress(train_files):
    env = make("Escape", train_files[:1])
    assert push(env, (1, 0), steps=25) > 0.1
    env.reset(seed=0)
    _teleport(env, 5.0, 0.0)
    assert push(env, (-1, 0), steps=25) < -0.1


def test_exploration_rewards_new_cells_only(train_files):
    env = make("Exploration", train_files[:1])
    # As in the reference, the grid starts empty: the first step finds the start cell, then
    # standing still finds nothing new.
    assert [env.step(ZERO)[1] for _ in range(10)] == [1.0] + [0.0] * 9
    gained = push(env, (1, 1), steps=40)
    visited = env.unwrapped.task.metrics(env.unwrapped.robot)["cells_visited"]
    assert gained >= 1.0 and gained == visited - 1


def _teleport(env, x: float, y: float) -> None:
    u = env.unwrapped
    u.data.qpos[:2] = (x, y)
    u.data.qpos[2] = u.task.arena.ground_height(x, y) + u.morphology.torso_height + 0.05


def test_corridor_edge_terminates(train_files):
    env = make("VT", train_files[:1])
    _teleport(env, 1.0, 19.5)
    _, _, terminated, _, info = env.step(ZERO)
    assert terminated and info["termination"] == "edge"


def test_escape_terminates_with_the_bonus(train_files):
    env = make("Escape", train_files[:1])
    _teleport(env, 42.5, 0.0)
    _, reward, terminated, _, info = env.step(ZERO)
    assert terminated and info["termination"] == "escaped"
    assert info["reward_escape"] == 100.0 and reward > 100.0


def test_patrol_goal_toggles_when_reached(train_files):
    env = make("Patrol", train_files[:1])
    _teleport(env, 5.0, 0.1)
    obs, reward, _, _, info = env.step(ZERO)
    assert info["reward_at_goal"] == 10.0 and info["goals_reached"] == 1
    assert env.unwrapped.task.goal[0] == -5.0
    # The reaching step still observes the goal it reached (the reference toggles after building
    # the observation); the next step observes the new one, 10 m behind.
    assert np.linalg.norm(obs["goal"][:2]) < 0.5
    obs = env.step(ZERO)[0]
    assert np.linalg.norm(obs["goal"][:2]) > 9.0


def test_box_tasks_reward_pushing_the_box_to_the_goal(train_files):
    env = make("ManipulateBox", train_files[:1])
    u = env.unwrapped
    u.task.reached = True  # skip the reach phase
    box_qpos = u.task._box_qpos
    step_towards = 0.02 * (u.task.goal[:2] - box_qpos[:2]) / np.linalg.norm(u.task.goal[:2] - box_qpos[:2])
    gains = []
    for sign in (1, -1):
        box_qpos[:2] += sign * step_towards
        info = env.step(ZERO)[-1]
        gains.append(info["reward_push"])
    assert gains[0] > 0 > gains[1]


@pytest.mark.parametrize("task", ["ManipulateBox", "PushBoxIncline"])
def test_box_reach_shaping_continues_after_the_box_is_reached(train_files, task):
    """As in DERL: the reach term is paid every step (walking away from the box after reaching it
    costs reward) and the push term starts on the very step the box is reached."""
    env = make(task, train_files[:1])
    u = env.unwrapped
    box = u.data.xpos[u.task._box].copy()
    torso_xy = u.robot.torso_qpos[:2].copy()
    # Put the torso right next to the box: this step reaches it.
    u.data.qpos[:2] = box[:2] - 0.3 * (box[:2] - torso_xy) / np.linalg.norm(box[:2] - torso_xy)
    u.data.qpos[2] += box[2] - u.robot.torso_qpos[2] + 0.3
    # ... and the box moves 2 cm toward the goal on the same step: already paid as push.
    to_goal = u.task.goal[:2] - box[:2]
    u.task._box_qpos[:2] += 0.02 * to_goal / np.linalg.norm(to_goal)
    mujoco.mj_forward(u.model, u.data)
    info = env.step(ZERO)[-1]
    assert info["reward_reached"] == 10.0 and info["reward_reach"] > 0
    assert info["reward_push"] > 0.5 and u.task.reached
    # Walking away from the reached box is penalised by the reach term.
    away = push(env, -(box[:2] - torso_xy), steps=10)
    assert away < -1.0


def _yaw(env, angle: float) -> None:
    u = env.unwrapped
    u.data.qpos[3:7] = (math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2))
    mujoco.mj_forward(u.model, u.data)
    u.robot.sync()


def test_height_map_shows_a_step_ahead_at_the_right_offset(train_files):
    env = make("VT", train_files[:1])
    u = env.unwrapped
    grid = u.task.arena.grid
    grid.heights[:] = 0.0
    x0, y0, _ = u.robot.torso_qpos.tolist()
    grid.heights[:, grid.columns_at(x0 + 2.0) :] = 0.5  # a 0.5 m step starting 2 m ahead
    grid.upload(u.model)
    hmap = u._observation()["hfield"].reshape(C.HFIELD_ROWS, C.HFIELD_COLS)
    ahead = FORWARD_CELLS >= 21
    behind = FORWARD_CELLS <= 19
    assert np.allclose(hmap[:, ahead], 0.5) and np.allclose(hmap[:, behind], 0.0)
    # Facing +y, the step (world +x) is on the robot's right: negative lateral offsets.
    _yaw(env, math.pi / 2)
    hmap = u._observation()["hfield"].reshape(C.HFIELD_ROWS, C.HFIELD_COLS)
    assert np.allclose(hmap[LATERAL_CELLS <= -21], 0.5)
    assert np.allclose(hmap[(LATERAL_CELLS >= -19) & (LATERAL_CELLS <= 19)], 0.0)
    assert np.allclose(hmap[LATERAL_CELLS >= 40], -11.0)  # 4 m to the left is off the course (reference: -11)


def test_height_map_matches_the_physical_terrain(train_files):
    """No y-mirror: a ray cast down onto the heightfield hits the heights the robot observes."""
    env = make("VT", train_files[:1])
    u = env.unwrapped
    grid = u.task.arena.grid
    rng = np.random.default_rng(0)
    grid.heights[:] = 0.0
    grid.heights[:, 100:400] = rng.uniform(0.0, 1.0, size=(grid.heights.shape[0], 300))
    grid.upload(u.model)
    geom = np.zeros(1, dtype=np.int32)
    for row, col in zip(rng.integers(50, 350, 20), rng.integers(110, 390, 20)):
        x, y = grid.x0 + col * grid.resolution, grid.y0 + row * grid.resolution  # sample points
        distance = mujoco.mj_ray(u.model, u.data, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, u.robot.torso_id, geom)
        assert 5.0 - distance == pytest.approx(grid.heights[row, col], abs=1e-4)
        assert grid.height(x + 0.03, y - 0.03) == grid.heights[row, col]


def test_obstacles_appear_in_the_height_map(train_files):
    env = make("Obstacle", train_files[:1])
    u = env.unwrapped
    arena = u.task.arena
    placed = arena.layout[arena.layout[:, 2] > 0]
    assert len(placed) >= 40
    for x, y, _, sx, sy, _ in placed[:10]:
        assert arena.grid.height(x, y) == pytest.approx(2.0)  # the reference's observed block height
        assert arena.grid.height(x + sx, y - sy) == pytest.approx(2.0)  # a corner of its footprint
    assert arena.grid.height(0.0, 0.0) == 0.0
    assert arena.grid.height(arena.bounds[0] - 0.5, 0.0) == pytest.approx(3.0)  # walls: +3 as in the reference


@pytest.mark.parametrize("task, key", [("PointNav", "goal"), ("Patrol", "goal"), ("ManipulateBox", "object")])
def test_goal_and_object_vectors_rotate_with_the_torso(train_files, task, key):
    env = make(task, train_files[:1])
    u = env.unwrapped
    _yaw(env, 0.0)
    before = u._observation()[key].reshape(-1, 3)[0]
    _yaw(env, math.pi / 2)
    after = u._observation()[key].reshape(-1, 3)[0]
    # Rotating the torso by +90 deg about z turns torso-frame vectors by -90 deg.
    np.testing.assert_allclose(after[:2], [before[1], -before[0]], atol=1e-4)
    assert np.linalg.norm(before) > 1.0


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_every_id_passes_check_env_with_the_same_spaces(train_files, env_id, monkeypatch):
    """Gymnasium's checker, render check included, passes on every id on a machine without a display:
    each env lists only the render modes it can serve (break: MultiTask's class metadata, which lists
    ``human`` -> "render_mode='human' needs a display")."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    env = gym.make(env_id, morphologies=train_files[:2])
    assert env.metadata["render_modes"] == ["rgb_array"]
    check_env(env.unwrapped)
    # Stable-Baselines3's checker passes too; its only warnings are the ones docs/environments.md explains
    import warnings

    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_check_env(env)
    unexplained = [str(w.message) for w in caught if "unconventional shape" not in str(w.message) and "Box" not in str(w.message)]
    assert not unexplained, unexplained
    assert env.observation_space == C.observation_space() and env.action_space == C.action_space()


def test_task_observation_keys(train_files):
    uses = {
        "hfield": {"VT", "Obstacle", "Escape"},
        "goal": {"Patrol", "PointNav", "PushBoxIncline", "ManipulateBox"},
        "object": {"PushBoxIncline", "ManipulateBox"},
    }
    for task in TASKS:
        # the declared keys (what an exported single-task actor keeps) are the ones the task fills
        assert set(TASKS[task].observation_keys) == {key for key, tasks in uses.items() if task in tasks}, task
        env = gym.make(unimal_envs.env_id(task), morphologies=train_files[:1])
        obs, _ = env.reset(seed=0)
        for key, tasks in uses.items():
            if task not in tasks:
                assert not np.any(obs[key]), (task, key)
            elif key == "hfield":  # VT starts on 6 m of flat ground: its first map may be all zeros
                assert env.unwrapped.task.arena.has_height_map
            else:
                assert np.any(obs[key]), (task, key)
        assert obs["task_index"][0] == C.TASK_NAMES.index(task)


def test_terrain_is_redrawn_every_episode(train_files):
    env = make("VT", train_files[:1])
    first = env.unwrapped.task.arena.grid.heights.copy()
    env.reset(seed=1)
    assert not np.array_equal(first, env.unwrapped.task.arena.grid.heights)
    env.reset(seed=0)
    np.testing.assert_array_equal(first, env.unwrapped.task.arena.grid.heights)


def test_multitask_draws_tasks_and_reports_them(train_files):
    env = gym.make("Unimal-MultiTask-v1", morphologies=train_files[:2])
    seen = set()
    for seed in range(30):
        obs, info = env.reset(seed=seed)
        seen.add(info["task"])
        assert C.TASK_NAMES[int(obs["task_index"][0])] == info["task"]
        assert env.step(ZERO)[-1]["task"] == info["task"]
    assert seen == set(C.TRAIN_TASKS)
    assert env.reset(options={"task": "VT"})[1]["task"] == "VT"
    with pytest.raises(ValueError, match="not one of this env's tasks"):
        env.reset(options={"task": "Escape"})
    with pytest.raises(ValueError, match="unknown"):
        gym.make("Unimal-MultiTask-v1", tasks=["FT", "Swim"], morphologies=train_files[:1])


def test_each_id_is_its_tasks_current_version_and_an_old_id_names_the_new_one():
    """Obstacle's blocks became solid (dynamics changed): its id moved to v1, and so did MultiTask's, which draws
    Obstacle episodes; the old ids fail naming the new; every docstring's Version History has the current version."""
    registered = {spec.id for spec in gym.registry.values() if spec.id.startswith("Unimal-")}
    assert registered == set(ALL_IDS) and unimal_envs.MULTITASK_ID in registered
    assert unimal_envs.env_id("Obstacle") == "Unimal-Obstacle-v1" and unimal_envs.env_id("FT") == "Unimal-FT-v0"
    for old, new in (("Unimal-Obstacle-v0", "Unimal-Obstacle-v1"), ("Unimal-MultiTask-v0", "Unimal-MultiTask-v1")):
        with pytest.raises(gym.error.DeprecatedEnv, match=new):
            gym.make(old)
    for cls in [*TASKS.values(), unimal_envs.MultiTaskEnv]:
        history = cls.__doc__.split("Version History:")[1]
        assert f"* v{cls.version}:" in history and "* v0:" in history, cls.__name__
    assert unimal_envs.task_of("Unimal-Obstacle-v1") == "Obstacle" and unimal_envs.task_of("Unimal-FT-v0-metamorph") == "FT"
    with pytest.raises(ValueError, match="outdated version.*'Unimal-Obstacle-v1'"):
        unimal_envs.task_of("Unimal-Obstacle-v0")
    with pytest.raises(ValueError, match="not a Unimal env id"):
        unimal_envs.task_of("Ant-v5")


@pytest.mark.parametrize(
    "before, after",
    [({}, "egl"), ({"DISPLAY": ":0"}, None), ({"MUJOCO_GL": "glfw"}, "glfw")],
)
def test_importing_sets_mujoco_gl_only_when_headless_and_unset(before, after):
    """The one change to the process environment, documented in the package docstring: ``MUJOCO_GL=egl`` when
    there is no display and the user chose no backend; otherwise the environment is left as it was."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "PYOPENGL_PLATFORM")} | before
    shown = subprocess.run(
        [sys.executable, "-c", "import os, unimal_envs; print(os.environ.get('MUJOCO_GL'))"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()[-1]
    assert shown == str(after)
    assert "MUJOCO_GL" in unimal_envs.__doc__
