"""Peg insertion: pick up a square peg and lower it into the square hole of a fixture."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint, equivalent_yaw
from ..robot import RobotConfig
from ..scene import add_free_box
from .base import COLORS, Task, body_yaw, sample_separated, set_free_body_pose, yaw_features
from .fixtures import add_walled_square, local_xyz, set_mocap_pose
from .grasping import grasp_yaw, pick_and_place

PEG_HALF = (0.01, 0.01, 0.04)  # 2 x 2 x 8 cm
HOLE_HALF = 0.0125  # 2.5 mm clearance on each side of the peg
FIXTURE_HALF = 0.05
FIXTURE_HEIGHT = 0.03  # the hole is this deep, down to the table
INSERTION_DEPTH = 0.02  # success once the peg's bottom is this far below the fixture's top
GRASP_HEIGHT = 0.01  # above the centre, so the fingers clear the fixture; higher, the peg swings in the grasp
_TEMPLATES = (
    "insert the {color} peg into the hole",
    "put the {color} peg in the square hole of the {fixture} block",
    "pick up the {color} peg and insert it into the hole",
)
_AREA = (np.array([0.38, -0.22]), np.array([0.6, 0.22]))


class PegInsert(Task):
    name = "peg_insert"
    category = "other"
    max_episode_steps = 200
    environment_state_dim = 10  # peg xyz, fixture xyz, then their yaws (sin, cos of 4 x yaw: both are square)

    def build(self, spec: mujoco.MjSpec) -> None:
        add_free_box(spec, "peg", PEG_HALF, mass=0.05)
        add_walled_square(spec, "fixture", HOLE_HALF, FIXTURE_HALF, FIXTURE_HEIGHT)

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._pinch = robot.end_effectors[0].site
        self._fixture_geoms = [model.geom(f"fixture_wall_{i}").id for i in range(4)]

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        peg_xy, fixture_xy = sample_separated(rng, 2, *_AREA, min_distance=0.17)
        peg_color, fixture_color = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("peg").rgba = COLORS[peg_color]
        model.geom_rgba[self._fixture_geoms] = COLORS[fixture_color]
        set_free_body_pose(data, "peg", np.r_[peg_xy, PEG_HALF[2]], rng.uniform(-np.pi / 4, np.pi / 4))
        set_mocap_pose(model, data, "fixture", fixture_xy, rng.uniform(-np.pi / 4, np.pi / 4))
        return str(rng.choice(_TEMPLATES)).format(color=peg_color, fixture=fixture_color)

    def _peg_in_hole(self, data: mujoco.MjData) -> tuple[np.ndarray, float]:
        """The peg's xy offset from the hole's axis (fixture frame) and its bottom's depth below the top."""
        local = local_xyz(data, "fixture", "peg")
        return local[:2], FIXTURE_HEIGHT - (local[2] - PEG_HALF[2])

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        offset, depth = self._peg_in_hole(data)
        return bool(np.all(np.abs(offset) < HOLE_HALF) and depth > INSERTION_DEPTH)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        peg = data.body("peg").xpos
        offset, depth = self._peg_in_hole(data)
        reach = np.exp(-10 * np.linalg.norm(eef_pos - (peg + [0, 0, GRASP_HEIGHT])))
        lifted = float(peg[2] > PEG_HALF[2] + 0.02)
        align = np.exp(-20 * np.linalg.norm(offset))
        insert = np.clip(depth / INSERTION_DEPTH, 0.0, 1.0) * float(np.all(np.abs(offset) < HOLE_HALF))
        return float(0.2 * reach + 0.2 * lifted + 0.3 * align * (lifted or insert > 0) + 0.25 * insert)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        bodies = ("peg", "fixture")
        return np.concatenate([*(data.body(b).xpos for b in bodies), *(yaw_features(data, b) for b in bodies)])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        yaw = grasp_yaw(data, "peg")
        # The held peg keeps the gripper's yaw (up to its square symmetry): turn it to the hole's.
        place_yaw = equivalent_yaw(body_yaw(data, "fixture"), yaw)
        seated = data.body("fixture").xpos + [0, 0, PEG_HALF[2] + 0.002]
        return pick_and_place(data, "peg", self._pinch, seated, yaw, place_yaw, grasp_height=GRASP_HEIGHT,
                              place_tolerance=0.003, place_speed=0.3)
