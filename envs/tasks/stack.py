"""Stack: put one named cube on top of another, beside a distractor cube."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint, equivalent_yaw
from ..robot import RobotConfig
from ..scene import add_free_box
from .base import COLORS, Task, body_yaw, geoms_touch, sample_separated, set_free_body_pose, yaw_features
from .grasping import grasp_yaw, gripper_geoms, pick_and_place

CUBE_HALF = 0.02
CUBES = ("top_cube", "bottom_cube", "distractor_cube")
XY_TOLERANCE = 0.02  # a cube this far off-centre still rests flat on the one below
_TEMPLATES = (
    "stack the {top} cube on the {bottom} cube",
    "put the {top} block on top of the {bottom} block",
    "place the {top} cube onto the {bottom} cube",
)
_AREA = (np.array([0.35, -0.25]), np.array([0.62, 0.25]))


class Stack(Task):
    name = "stack"
    category = "other"
    max_episode_steps = 200
    environment_state_dim = 15  # top, bottom and distractor cube xyz, then their yaws (sin, cos of 4 x yaw)

    def build(self, spec: mujoco.MjSpec) -> None:
        for cube in CUBES:
            add_free_box(spec, cube, (CUBE_HALF,) * 3)

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._gripper_geoms = gripper_geoms(model, robot)
        self._top_geom = np.array([model.geom("top_cube").id])
        self._pinch = robot.end_effectors[0].site

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        positions = sample_separated(rng, len(CUBES), *_AREA, min_distance=0.12)
        colors = rng.choice(list(COLORS), size=len(CUBES), replace=False)
        for cube, color, xy in zip(CUBES, colors, positions):
            model.geom(cube).rgba = COLORS[color]
            set_free_body_pose(data, cube, np.r_[xy, CUBE_HALF], rng.uniform(-np.pi / 4, np.pi / 4))
        return str(rng.choice(_TEMPLATES)).format(top=colors[0], bottom=colors[1])

    def _stacked(self, data: mujoco.MjData) -> bool:
        offset = data.body("top_cube").xpos - data.body("bottom_cube").xpos
        return bool(np.linalg.norm(offset[:2]) < XY_TOLERANCE and abs(offset[2] - 2 * CUBE_HALF) < 0.005)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._stacked(data) and not geoms_touch(data, self._gripper_geoms, self._top_geom)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        top, bottom = data.body("top_cube").xpos, data.body("bottom_cube").xpos
        reach = np.exp(-10 * np.linalg.norm(eef_pos - top))
        align = np.exp(-10 * np.linalg.norm(top[:2] - bottom[:2]))
        lifted = float(top[2] > bottom[2] + CUBE_HALF)
        return float(0.25 * reach + 0.25 * lifted + 0.45 * align * lifted)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([*(data.body(cube).xpos for cube in CUBES),
                               *(yaw_features(data, cube) for cube in CUBES)])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        yaw = grasp_yaw(data, "top_cube")

        def on_bottom() -> np.ndarray:
            return data.body("bottom_cube").xpos + [0, 0, 2 * CUBE_HALF + 0.005]

        # Line the faces up with the bottom cube's so the stack rests flat.
        place_yaw = equivalent_yaw(body_yaw(data, "bottom_cube"), yaw)
        return pick_and_place(data, "top_cube", self._pinch, on_bottom, yaw, place_yaw,
                              place_tolerance=0.005)
