"""Humanoid pick-and-place: grasp the named can from its side and stand it on the plate."""

from __future__ import annotations

import mujoco
import numpy as np

from ...experts import Step
from ...scene import GEOM, add_free_cylinder
from ..base import COLORS, sample_separated, set_free_body_pose
from .hands import HumanoidTask, hand_for, side_area

CAN_RADIUS = 0.028
CAN_HALF_HEIGHT = 0.06
PLATE_RADIUS = 0.075
PLATE_HALF_HEIGHT = 0.005
CANS = ("target_can", "distractor_can")
_TEMPLATES = (
    "put the {color} can on the plate",
    "pick up the {color} can and place it on the plate",
    "move the {color} can onto the plate",
)
_X_RANGE = (0.0, 0.17)
# side * y: the can stands on the acting hand's half of the table; the plate may reach past the middle.
_CAN_SIDE_RANGE = (0.03, 0.24)
_PLATE_SIDE_RANGE = (-0.06, 0.24)
_DISTRACTOR_SIDE_RANGE = (0.1, 0.22)  # on the other half
_MIN_CARRY = 0.15


class HumanoidPickPlace(HumanoidTask):
    name = "pick_place"
    category = "pick_and_place"
    max_episode_steps = 200
    environment_state_dim = 9  # target can xyz, distractor can xyz, plate xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        for can in CANS:
            add_free_cylinder(spec, can, CAN_RADIUS, CAN_HALF_HEIGHT, mass=0.1)
        plate = spec.worldbody.add_body(name="plate", mocap=True)
        plate.add_geom(name="plate", type=GEOM.mjGEOM_CYLINDER, size=(PLATE_RADIUS, PLATE_HALF_HEIGHT, 0),
                       pos=(0, 0, PLATE_HALF_HEIGHT), rgba=(0.95, 0.95, 0.92, 1))

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._can_geom = np.array([model.geom("target_can").id])

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        side = rng.choice([-1.0, 1.0])  # +1: the left hand acts; the distractor stands on the other half
        can_xy = rng.uniform(*side_area(side, _X_RANGE, _CAN_SIDE_RANGE))
        (plate_xy,) = sample_separated(rng, 1, *side_area(side, _X_RANGE, _PLATE_SIDE_RANGE), _MIN_CARRY,
                                       fixed=(can_xy,))
        distractor_xy = rng.uniform(*side_area(-side, _X_RANGE, _DISTRACTOR_SIDE_RANGE))
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_can").rgba = COLORS[target]
        model.geom("distractor_can").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_can", np.r_[can_xy, CAN_HALF_HEIGHT])
        set_free_body_pose(data, "distractor_can", np.r_[distractor_xy, CAN_HALF_HEIGHT])
        data.mocap_pos[model.body("plate").mocapid[0]] = np.r_[plate_xy, 0.0]
        return str(rng.choice(_TEMPLATES)).format(color=target)

    def _on_plate(self, data: mujoco.MjData) -> bool:
        can, plate = data.body("target_can").xpos, data.body("plate").xpos
        resting_height = plate[2] + 2 * PLATE_HALF_HEIGHT + CAN_HALF_HEIGHT
        return bool(np.linalg.norm(can[:2] - plate[:2]) < PLATE_RADIUS - 0.01 and abs(can[2] - resting_height) < 0.01)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._on_plate(data) and not any(self.touches(data, hand, self._can_geom) for hand in (0, 1))

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        can, plate = data.body("target_can").xpos, data.body("plate").xpos
        reach = np.exp(-10 * np.linalg.norm(self.palm(data, hand_for(can)) - can))
        place = np.exp(-10 * np.linalg.norm(can[:2] - plate[:2]))
        lifted = float(can[2] > CAN_HALF_HEIGHT + 0.02)
        return float(0.25 * reach + 0.25 * lifted + 0.45 * place * (lifted or self._on_plate(data)))

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body(b).xpos for b in (*CANS, "plate")])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        goal = data.body("plate").xpos + [0, 0, 2 * PLATE_HALF_HEIGHT + CAN_HALF_HEIGHT + 0.01]
        return self.carry(data, "target_can", goal)
