"""Camera images are real renders that show the robot and the task's objects."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from conftest import FRANKA_TASKS
from dust_rl.envs import DustEnv


def _visible_geoms(env: DustEnv, camera: str) -> set[int]:
    renderer = mujoco.Renderer(env.model, *env.image_shape[:2])
    renderer.enable_segmentation_rendering()
    renderer.update_scene(env.data, camera)
    ids = renderer.render()[..., 0]
    renderer.close()
    return set(np.unique(ids[ids >= 0]).tolist())


@pytest.mark.parametrize("task", FRANKA_TASKS)
def test_front_camera_shows_task_objects(task):
    env = DustEnv(task=task, image_size=96)
    obs, _ = env.reset(seed=0)
    for camera in env.cameras:
        image = obs[f"observation.image.{camera}"]
        assert image.std() > 10, f"{camera} image looks blank"
    scenery = {"floor", "table"}
    task_geoms = {g for g in range(env.model.ngeom)
                  if not env.model.body(env.model.geom_bodyid[g]).name.startswith("panda/")
                  and env.model.geom(g).name not in scenery}
    assert task_geoms & _visible_geoms(env, "front"), "no task object visible in the front camera"
    env.close()


def test_wrist_camera_sees_fingers_and_moves(rgb_env):
    obs, _ = rgb_env.reset(seed=0)
    before = obs["observation.image.wrist"].astype(int)
    for _ in range(5):
        obs = rgb_env.step(np.array([0, 0.8, 0, 0, 0, 0, -1], np.float32))[0]
    assert np.abs(obs["observation.image.wrist"].astype(int) - before).mean() > 2
