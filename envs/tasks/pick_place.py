"""Pick-and-place: put the named cube on the plate, beside a distractor cube."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from ..robot import RobotConfig
from ..scene import GEOM, add_free_box
from .base import COLORS, Task, geoms_touch, sample_separated, set_free_body_pose, yaw_features
from .grasping import grasp_yaw, gripper_geoms, pick_and_place

CUBE_HALF = 0.02
PLATE_RADIUS = 0.07
PLATE_HALF_HEIGHT = 0.005
_TEMPLATES = (
    "put the {color} cube on the plate",
    "place the {color} block onto the plate",
    "pick up the {color} cube and set it on the plate",
)
_AREA = (np.array([0.35, -0.25]), np.array([0.62, 0.25]))


class PickPlace(Task):
    name = "pick_place"
    category = "pick_and_place"
    max_episode_steps = 200
    environment_state_dim = 13  # target cube xyz, distractor xyz, plate xyz, then the cubes' yaws (sin, cos of 4 x yaw)

    def build(self, spec: mujoco.MjSpec) -> None:
        add_free_box(spec, "target_cube", (CUBE_HALF,) * 3)
        add_free_box(spec, "distractor_cube", (CUBE_HALF,) * 3)
        plate = spec.worldbody.add_body(name="plate", mocap=True)
        plate.add_geom(name="plate", type=GEOM.mjGEOM_CYLINDER, size=(PLATE_RADIUS, PLATE_HALF_HEIGHT, 0),
                       pos=(0, 0, PLATE_HALF_HEIGHT), rgba=(0.95, 0.95, 0.92, 1))

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._gripper_geoms = gripper_geoms(model, robot)
        self._cube_geom = np.array([model.geom("target_cube").id])
        self._pinch = robot.end_effectors[0].site

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        cube_xy, distractor_xy, plate_xy = sample_separated(rng, 3, *_AREA, min_distance=0.13)
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_cube").rgba = COLORS[target]
        model.geom("distractor_cube").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_cube", np.r_[cube_xy, CUBE_HALF], rng.uniform(-np.pi / 4, np.pi / 4))
        set_free_body_pose(data, "distractor_cube", np.r_[distractor_xy, CUBE_HALF], rng.uniform(-np.pi / 4, np.pi / 4))
        data.mocap_pos[model.body("plate").mocapid[0]] = np.r_[plate_xy, 0.0]
        return str(rng.choice(_TEMPLATES)).format(color=target)

    def _on_plate(self, data: mujoco.MjData) -> bool:
        cube, plate = data.body("target_cube").xpos, data.body("plate").xpos
        resting_height = plate[2] + 2 * PLATE_HALF_HEIGHT + CUBE_HALF
        return bool(np.linalg.norm(cube[:2] - plate[:2]) < PLATE_RADIUS - 0.01
                    and abs(cube[2] - resting_height) < 0.01)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._on_plate(data) and not geoms_touch(data, self._gripper_geoms, self._cube_geom)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        cube, plate = data.body("target_cube").xpos, data.body("plate").xpos
        reach = np.exp(-10 * np.linalg.norm(eef_pos - cube))
        place = np.exp(-10 * np.linalg.norm(cube[:2] - plate[:2]))
        lifted = float(cube[2] > CUBE_HALF + 0.02)
        return float(0.25 * reach + 0.25 * lifted + 0.45 * place * (lifted or self._on_plate(data)))

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        cubes = ("target_cube", "distractor_cube")
        return np.concatenate([*(data.body(b).xpos for b in (*cubes, "plate")),
                               *(yaw_features(data, b) for b in cubes)])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        def on_plate() -> np.ndarray:
            return data.body("plate").xpos + [0, 0, 2 * PLATE_HALF_HEIGHT + CUBE_HALF + 0.005]

        return pick_and_place(data, "target_cube", self._pinch, on_plate, grasp_yaw(data, "target_cube"))
