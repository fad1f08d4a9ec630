"""Rendered frames show the ground under the robot and every task's staged frame renders."""

from __future__ import annotations

import pytest

import unimal_envs
from unimal_envs.env import UnimalEnv
from unimal_envs.morphology.loader import morphology_files


@pytest.mark.parametrize("task", ["FT", "Obstacle"])
def test_the_ground_reaches_the_bottom_of_a_close_tracking_frame(task):
    """The near clipping plane is a few centimetres from the camera, not a fraction of the arena's
    extent: with MuJoCo's default (0.01 x 280 m) a camera 4 m from the robot cut the ground out of
    the bottom of the frame, which showed a band of sky there."""
    env = UnimalEnv(task, morphologies=morphology_files("train")[:1], render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    env.camera_distance, env.camera_angles = 2.5, (135.0, -30.0)
    env.render()
    renderer = env._world.renderer
    renderer.enable_depth_rendering()
    renderer.update_scene(env.data, camera=env._camera(env._world))
    depth = renderer.render()  # metres from the camera; nothing drawn = the far plane
    renderer.disable_depth_rendering()
    assert depth[-3:].max() < 10.0, "nothing is drawn at the bottom of the frame (the ground was clipped)"
    env.close()


def test_every_task_has_a_staged_frame():
    from unimal_envs.gallery import render_tasks

    frames = render_tasks("train-000", width=64, height=48)
    assert [task for task, _ in frames] == list(unimal_envs.tasks.TASKS)
    assert all(frame.shape == (48, 64, 3) and frame.std() > 5 for _, frame in frames)


@pytest.mark.parametrize("task", list(unimal_envs.tasks.TASKS))
def test_the_robot_is_in_every_staged_frame(task):
    """Each task's gallery frame shows the robot: hiding the robot's geoms changes the picture (the
    ManipulateBox frame once framed box and goal 20-30 m apart and showed neither robot nor box)."""
    import gymnasium as gym

    from unimal_envs.gallery import stage

    env = gym.make(unimal_envs.env_id(task), morphologies=morphology_files("train")[:1], render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    stage(env, task)
    shown = env.render().copy()
    base = env.unwrapped
    robot_bodies = range(base.robot.torso_id, base.robot.torso_id + base.robot.num_tokens)
    robot_geoms = [g for g in range(base.model.ngeom) if base.model.geom_bodyid[g] in robot_bodies]
    base.model.geom_rgba[robot_geoms, 3] = 0.0
    hidden = env.render()
    env.close()
    changed = (shown != hidden).any(axis=-1).mean()
    assert changed > 0.003, f"the {task} frame barely shows the robot ({changed:.2%} of its pixels)"
