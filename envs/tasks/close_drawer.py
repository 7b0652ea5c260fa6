"""Close drawer: push the cabinet's open drawer shut."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from .drawer_cabinet import MAX_OPENING, DrawerCabinetTask

CLOSED_TOLERANCE = 0.02
_START_OPENING = (0.10, MAX_OPENING)
_OVERSHOOT = 0.03  # the expert aims past the closed position so it keeps pushing until the drawer is shut
_TEMPLATES = (
    "close the {color} drawer",
    "push the {color} drawer shut",
    "push the drawer closed",
)


class CloseDrawer(DrawerCabinetTask):
    name = "close_drawer"

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        color = self.place_cabinet(model, data, rng, opening=rng.uniform(*_START_OPENING))
        return str(rng.choice(_TEMPLATES)).format(color=color)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self.opening(data) <= CLOSED_TOLERANCE

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        reach = np.exp(-10 * np.linalg.norm(eef_pos - self.slot_point(data)))
        shut = np.clip((MAX_OPENING - self.opening(data)) / (MAX_OPENING - CLOSED_TOLERANCE), 0.0, 1.0)
        return float(0.3 * reach + 0.65 * shut)

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        # Pushing from the slot behind the bar (on the drawer front) rather than in front of the bar
        # keeps the hand a handle's depth further from the robot base when the drawer is far out.
        yaw = self.cabinet_yaw(data)
        slot = self.slot_point(data)
        shut = slot - self.outward(data) * (self.opening(data) + _OVERSHOOT)
        return [
            Waypoint(slot + [0, 0, 0.08], closure=1.0, yaw=yaw, tolerance=0.015),
            Waypoint(slot, closure=1.0, yaw=yaw, tolerance=0.006, speed=0.5),
            Waypoint(shut, closure=1.0, yaw=yaw, tolerance=0.01, speed=0.5),
        ]
