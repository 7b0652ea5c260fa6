"""Place in basket: drop the can or carton named by colour and shape into a basket."""

from __future__ import annotations

import mujoco
import numpy as np

from ...experts import Step, equivalent_yaw
from ...scene import add_free_box, add_free_cylinder, add_open_box
from ..base import COLORS, body_yaw, set_free_body_pose
from .hands import HumanoidTask, hand_for, side_area

OBJECT_HALF = (0.028, 0.06)  # can radius / carton half width, half height
OBJECTS = (("can", "can"), ("carton", "carton"))  # body, shape word
BASKET_INNER_HALF = 0.085
BASKET_WALL_THICKNESS = 0.01
BASKET_WALL_HEIGHT = 0.045
BASKET_FLOOR_HEIGHT = 0.004
DROP_CLEARANCE = 0.015  # the object's bottom is this far above the rim when the hand lets go
_TEMPLATES = (
    "put the {color} {shape} in the basket",
    "place the {color} {shape} into the basket",
    "pick up the {color} {shape} and drop it in the basket",
)
_X_RANGE = (0.0, 0.17)
# side * y: the object stands on the acting hand's half, the basket inward of it, so the hand,
# which comes down on the object's outer side, stays clear of the walls.
_OBJECT_SIDE_RANGE = (0.12, 0.24)
_BASKET_SIDE_LOW = -0.1
_BASKET_INWARD = 0.16  # least side * y distance from the object to the basket's centre
_DISTRACTOR_SIDE_RANGE = (0.1, 0.22)  # on the other half


class PlaceInBasket(HumanoidTask):
    name = "place_in_basket"
    category = "pick_and_place"
    max_episode_steps = 200
    environment_state_dim = 9  # target xyz, distractor xyz, basket xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        add_free_cylinder(spec, "can", OBJECT_HALF[0], OBJECT_HALF[1], mass=0.1)
        add_free_box(spec, "carton", (OBJECT_HALF[0], OBJECT_HALF[0], OBJECT_HALF[1]), mass=0.1)
        add_open_box(spec, "basket", BASKET_INNER_HALF, BASKET_WALL_THICKNESS, BASKET_WALL_HEIGHT,
                     BASKET_FLOOR_HEIGHT, rgba=(0.6, 0.45, 0.3, 1))

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._objects = [body for body, _ in OBJECTS]  # target first once reset
        self._target_geom = np.array([model.geom(self._objects[0]).id])

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        side = rng.choice([-1.0, 1.0])  # +1: the left hand acts; the distractor stands on the other half
        target_xy = rng.uniform(*side_area(side, _X_RANGE, _OBJECT_SIDE_RANGE))
        basket_side_range = (_BASKET_SIDE_LOW, side * target_xy[1] - _BASKET_INWARD)
        basket_xy = rng.uniform(*side_area(side, _X_RANGE, basket_side_range))
        distractor_xy = rng.uniform(*side_area(-side, _X_RANGE, _DISTRACTOR_SIDE_RANGE))
        target = int(rng.integers(len(OBJECTS)))
        self._objects = [OBJECTS[target][0], OBJECTS[1 - target][0]]
        self._target_geom = np.array([model.geom(self._objects[0]).id])
        colors = list(rng.permutation(list(COLORS))[:2])
        if rng.random() < 0.5:  # half the time both share a colour, so the shape word matters too
            colors[1] = colors[0]
        for body, color, xy in zip(self._objects, colors, (target_xy, distractor_xy)):
            model.geom(body).rgba = COLORS[color]
            set_free_body_pose(data, body, np.r_[xy, OBJECT_HALF[1]], rng.uniform(-np.pi / 4, np.pi / 4))
        mocap = model.body("basket").mocapid[0]
        data.mocap_pos[mocap] = np.r_[basket_xy, 0.0]
        yaw = rng.uniform(-np.pi / 6, np.pi / 6)
        data.mocap_quat[mocap] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        return str(rng.choice(_TEMPLATES)).format(color=colors[0], shape=OBJECTS[target][1])

    def _in_basket(self, data: mujoco.MjData) -> bool:
        basket = data.body("basket")
        local = basket.xmat.reshape(3, 3).T @ (data.body(self._objects[0]).xpos - basket.xpos)
        return bool(np.all(np.abs(local[:2]) < BASKET_INNER_HALF) and local[2] < BASKET_WALL_HEIGHT + OBJECT_HALF[1])

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._in_basket(data) and not any(self.touches(data, hand, self._target_geom) for hand in (0, 1))

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        target, basket = data.body(self._objects[0]).xpos, data.body("basket").xpos
        reach = np.exp(-10 * np.linalg.norm(self.palm(data, hand_for(target)) - target))
        place = np.exp(-10 * np.linalg.norm(target[:2] - basket[:2]))
        lifted = float(target[2] > OBJECT_HALF[1] + 0.02)
        return float(0.25 * reach + 0.25 * lifted + 0.45 * place * (lifted or self._in_basket(data)))

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body(b).xpos for b in (*self._objects, "basket")])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        target = self._objects[0]
        drop = data.body("basket").xpos + [0, 0, BASKET_WALL_HEIGHT + DROP_CLEARANCE + OBJECT_HALF[1]]
        # A carton is held with the palm flat on one of its faces.
        yaw = equivalent_yaw(body_yaw(data, target), 0.0) if target == "carton" else 0.0
        return self.carry(data, target, drop, yaw=yaw, place_tolerance=0.015)
