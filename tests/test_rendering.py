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
