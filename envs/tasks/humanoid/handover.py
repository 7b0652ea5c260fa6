"""Hand-over: one hand picks up the named bottle and passes it to the other hand.

The bottle is tall enough for two side grasps one above the other: the giving
hand holds its lower half, the receiving hand closes around its upper half,
then the giving hand lets go and backs away.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from ...experts import Step, Waypoint
from ...scene import add_free_cylinder
from ..base import COLORS, set_free_body_pose
from .hands import APPROACH, HAND_NAMES, HumanoidTask, beside, hand_for, park, side_area, side_grasp

BOTTLE_RADIUS = 0.028
BOTTLE_HALF_HEIGHT = 0.11
GIVER_GRASP = np.array([0.0, 0.0, -0.04])  # palm site relative to the bottle centre
RECEIVER_GRASP = np.array([0.0, 0.0, 0.065])
HANDOVER_POINT = np.array([0.12, 0.0, 0.22])  # bottle centre during the hand-over
LIFTED = 0.04  # the bottle's bottom must be this high for it to count as held
BOTTLES = ("target_bottle", "distractor_bottle")
_TEMPLATES = (
    "pass the {color} bottle from your {giver} hand to your {receiver} hand",
    "hand the {color} bottle over to your {receiver} hand",
    "pick up the {color} bottle with the {giver} hand and give it to the {receiver} hand",
)
# Each bottle stands in front of a resting hand's fingers, whose tips it would top.
_X_RANGE = (0.13, 0.2)
_SIDE_RANGE = (0.06, 0.2)  # side * y of each bottle; the target on the giving hand's half


class Handover(HumanoidTask):
    name = "handover"
    category = "other"
    max_episode_steps = 200
    environment_state_dim = 6  # target bottle xyz, distractor bottle xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        for bottle in BOTTLES:
            add_free_cylinder(spec, bottle, BOTTLE_RADIUS, BOTTLE_HALF_HEIGHT, mass=0.1)

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._bottle_geom = np.array([model.geom("target_bottle").id])
        self._giver = 0

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        side = rng.choice([-1.0, 1.0])  # +1: the left hand gives
        target_xy = rng.uniform(*side_area(side, _X_RANGE, _SIDE_RANGE))
        distractor_xy = rng.uniform(*side_area(-side, _X_RANGE, _SIDE_RANGE))
        self._giver = hand_for(target_xy)
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_bottle").rgba = COLORS[target]
        model.geom("distractor_bottle").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_bottle", np.r_[target_xy, BOTTLE_HALF_HEIGHT])
        set_free_body_pose(data, "distractor_bottle", np.r_[distractor_xy, BOTTLE_HALF_HEIGHT])
        return str(rng.choice(_TEMPLATES)).format(color=target, giver=HAND_NAMES[self._giver],
                                                  receiver=HAND_NAMES[1 - self._giver])

    def _held_by(self, data: mujoco.MjData, hand: int) -> bool:
        lifted = data.body("target_bottle").xpos[2] - BOTTLE_HALF_HEIGHT > LIFTED
        return lifted and self.touches(data, hand, self._bottle_geom)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._held_by(data, 1 - self._giver) and not self.touches(data, self._giver, self._bottle_geom)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        bottle = data.body("target_bottle").xpos
        giver, receiver = self.palm(data, self._giver), self.palm(data, 1 - self._giver)
        reach = np.exp(-10 * np.linalg.norm(giver - (bottle + GIVER_GRASP)))
        lifted = float(bottle[2] - BOTTLE_HALF_HEIGHT > LIFTED)
        to_point = np.exp(-10 * np.linalg.norm(bottle - HANDOVER_POINT))
        received = np.exp(-10 * np.linalg.norm(receiver - (bottle + RECEIVER_GRASP)))
        return float(0.15 * reach + 0.15 * lifted + 0.2 * to_point * lifted + 0.2 * received * lifted
                     + 0.25 * self._held_by(data, 1 - self._giver))

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body(b).xpos for b in BOTTLES])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        giver, receiver = self._giver, 1 - self._giver
        giver_site = self.palms[giver]
        bottle = data.body("target_bottle")

        def at_handover() -> np.ndarray:
            """Giver palm target that brings the bottle to the hand-over point, whatever its slip."""
            return HANDOVER_POINT + data.site(giver_site).xpos - bottle.xpos

        def holding() -> bool:
            return bool(np.linalg.norm(bottle.xpos + GIVER_GRASP - data.site(giver_site).xpos) < 0.03)

        def upper_grasp(offset: np.ndarray) -> Callable[[], np.ndarray]:
            """A point on the bottle's (possibly tilted) axis at the receiving grasp, plus ``offset``."""
            return lambda: bottle.xpos + bottle.xmat.reshape(3, 3) @ RECEIVER_GRASP + offset

        clear = beside(receiver, yaw=0.0)  # the open receiving hand comes down clear of the tilted bottle
        idle = park(receiver)
        steps = [(w, idle) for w in side_grasp(data, "target_bottle", giver_site, giver, GIVER_GRASP,
                                                approach=2 * BOTTLE_HALF_HEIGHT)]
        steps.append((Waypoint(at_handover, closure=1.0, tolerance=0.015, speed=0.7, requires=holding), idle))
        hold = Waypoint(at_handover, closure=1.0, tolerance=np.inf)
        steps += [
            (hold, Waypoint(upper_grasp(clear + APPROACH), closure=0.0, tolerance=0.02)),
            (hold, Waypoint(upper_grasp(clear), closure=0.0, tolerance=0.008, speed=0.5)),
            (hold, Waypoint(upper_grasp(np.zeros(3)), closure=0.0, tolerance=0.006, speed=0.5)),
            (hold, Waypoint(upper_grasp(np.zeros(3)), closure=1.0, tolerance=0.02, hold=8)),
            (Waypoint(at_handover, closure=0.0, tolerance=np.inf, hold=6),
             Waypoint(upper_grasp(np.zeros(3)), closure=1.0, tolerance=0.02)),
            # The giver backs off outward and down, away from the receiving hand.
            (Waypoint(HANDOVER_POINT + GIVER_GRASP + 3 * beside(giver, yaw=0.0) - [0, 0, 0.03], closure=0.0,
                      tolerance=0.02),
             Waypoint(upper_grasp(np.zeros(3)), closure=1.0, tolerance=np.inf)),
        ]
        return [step if giver == 0 else step[::-1] for step in steps]
