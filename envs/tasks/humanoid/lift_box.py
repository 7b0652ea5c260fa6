"""Bimanual lift: squeeze the named box between both palms and lift it off the table."""

from __future__ import annotations

import mujoco
import numpy as np

from ...experts import Step, Waypoint, equivalent_yaw
from ...g1 import OPEN_THUMB_BEHIND, PALM_DEPTH
from ...scene import add_free_box
from ..base import COLORS, body_yaw, set_free_body_pose
from .hands import APPROACH, LEFT, RIGHT, HumanoidTask

BOX_HALF = (0.035, 0.11, 0.07)  # shallow, wide and tall: one palm on each end, thumbs behind it
BOX_MASS = 0.4
LIFT_HEIGHT = 0.1  # success once the box's bottom is this high
MAX_TILT = np.deg2rad(20)
SQUEEZE = 0.02  # the palms aim this far inside the box's ends
TORSIONAL_FRICTION = 0.04  # m: a palm-sized contact patch
THUMB_CLEARANCE = 0.004  # between the open thumbs and the box's back
BOXES = ("target_box", "distractor_box")
_TEMPLATES = (
    "lift the {color} box with both hands",
    "pick up the {color} box using both hands",
    "hold the {color} box between your hands and lift it",
)
_AREA = (np.array([0.08, -0.06]), np.array([0.16, 0.06]))
_DISTRACTOR_X = (0.38, 0.44)  # behind the target, beyond the reach of the fingers around it
_YAW_RANGE = np.deg2rad(20)


class LiftBox(HumanoidTask):
    name = "lift_box"
    category = "other"
    max_episode_steps = 150
    environment_state_dim = 10  # target box xyz and quaternion, distractor box xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        for box in BOXES:
            geom = add_free_box(spec, box, BOX_HALF, mass=BOX_MASS).geoms[0]
            # Two flat palms grip over patches a few centimetres wide, which resists the box
            # pivoting about the line between them; MuJoCo models that as torsional friction.
            geom.friction[1] = TORSIONAL_FRICTION

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._box_geom = np.array([model.geom("target_box").id])

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        box_xy = rng.uniform(*_AREA)
        distractor_xy = np.array([rng.uniform(*_DISTRACTOR_X), -box_xy[1]])
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_box").rgba = COLORS[target]
        model.geom("distractor_box").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_box", np.r_[box_xy, BOX_HALF[2]], rng.uniform(-_YAW_RANGE, _YAW_RANGE))
        set_free_body_pose(data, "distractor_box", np.r_[distractor_xy, BOX_HALF[2]],
                           rng.uniform(-_YAW_RANGE, _YAW_RANGE))
        return str(rng.choice(_TEMPLATES)).format(color=target)

    def _lifted(self, data: mujoco.MjData) -> bool:
        box = data.body("target_box")
        level = box.xmat[8] > np.cos(MAX_TILT)
        return bool(box.xpos[2] - BOX_HALF[2] > LIFT_HEIGHT and level)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._lifted(data) and all(self.touches(data, hand, self._box_geom) for hand in (LEFT, RIGHT))

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        box = data.body("target_box").xpos
        ends = self._palm_targets(data, squeeze=0.0)
        reach = np.mean([np.exp(-10 * np.linalg.norm(self.palm(data, h) - ends[h])) for h in (LEFT, RIGHT)])
        height = np.clip((box[2] - BOX_HALF[2]) / LIFT_HEIGHT, 0.0, 1.0)
        return float(0.4 * reach + 0.55 * height)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        box = data.body("target_box")
        return np.concatenate([box.xpos, box.xquat, data.body("distractor_box").xpos])

    def _palm_targets(self, data: mujoco.MjData, squeeze: float, outward: float = 0.0,
                      up: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Left and right palm-site targets on the box's ends (box frame offsets, world result)."""
        box = data.body("target_box")
        rotation = box.xmat.reshape(3, 3)
        # The palms press where the open thumbs, which stick out of them, just clear the box's back.
        inset = BOX_HALF[1] - PALM_DEPTH - squeeze + outward
        along = OPEN_THUMB_BEHIND - BOX_HALF[0] - THUMB_CLEARANCE
        return tuple(box.xpos + rotation @ [along, sign * inset, 0.0] + [0.0, 0.0, up] for sign in (1.0, -1.0))

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        # Both palms face the box's ends: turn the hands with the box (it is symmetric under half a turn).
        yaw = equivalent_yaw(body_yaw(data, "target_box"), 0.0, period=np.pi)

        def both(tolerance: float, speed: float = 1.0, hold: int = 0, **offsets) -> tuple[Waypoint, Waypoint]:
            targets = self._palm_targets(data, **offsets)
            return tuple(Waypoint(t, closure=0.0, yaw=yaw, tolerance=tolerance, speed=speed, hold=hold)
                         for t in targets)

        # The fingers stay open: curling, they would hit the box's ends and push the palms off.
        # The box stops the palms short of their squeezing targets.
        return [
            both(0.02, squeeze=0.0, outward=0.04, up=APPROACH[2]),
            both(0.01, squeeze=0.0, outward=0.04, speed=0.6),
            both(SQUEEZE + 0.015, squeeze=SQUEEZE, speed=0.4, hold=4),
            both(SQUEEZE + 0.015, squeeze=SQUEEZE, up=LIFT_HEIGHT + 0.05, speed=0.5),
        ]
