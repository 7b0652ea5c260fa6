"""Camera images are real renders that show the robot and the task's objects."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from conftest import SUITE_TASKS

from dust_rl.envs import DustEnv


def _visible_geoms(env: DustEnv, camera: str) -> set[int]:
    renderer = mujoco.Renderer(env.model, *env.image_shape[:2])
    renderer.enable_segmentation_rendering()
    renderer.update_scene(env.data, camera)
    ids = renderer.render()[..., 0]
    renderer.close()
    return set(np.unique(ids[ids >= 0]).tolist())


@pytest.mark.parametrize(("robot", "task"), SUITE_TASKS)
def test_default_cameras_show_task_objects(robot, task):
    env = DustEnv(task=task, robot=robot, image_size=96)
    obs, _ = env.reset(seed=0)
    for camera in env.cameras:
        image = obs[f"observation.image.{camera}"]
        assert image.std() > 10, f"{camera} image looks blank"
    scenery = {"floor", "table"}
    robot_root = env.model.body_rootid[env.model.site(env.robot.end_effectors[0].site).bodyid[0]]
    task_geoms = {g for g in range(env.model.ngeom)
                  if env.model.body_rootid[env.model.geom_bodyid[g]] != robot_root
                  and env.model.geom(g).name not in scenery}
    main_camera = env.robot.default_cameras[0]  # Franka: front; humanoid: head
    assert task_geoms & _visible_geoms(env, main_camera), f"no task object visible in the {main_camera} camera"
    env.close()


def test_wrist_camera_sees_fingers_and_moves(rgb_env):
    obs, _ = rgb_env.reset(seed=0)
    before = obs["observation.image.wrist"].astype(int)
    for _ in range(5):
        obs = rgb_env.step(np.array([0, 0.8, 0, 0, 0, 0, -1], np.float32))[0]
    assert np.abs(obs["observation.image.wrist"].astype(int) - before).mean() > 2
