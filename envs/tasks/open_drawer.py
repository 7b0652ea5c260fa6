"""Open drawer: pull the cabinet's drawer out by its handle."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from .drawer_cabinet import DrawerCabinetTask

SUCCESS_OPENING = 0.10
_PULL_TO = 0.15  # the expert aims past the success threshold so damping cannot stall it short
_TEMPLATES = (
    "open the {color} drawer",
    "pull the {color} drawer open",
    "pull open the drawer",
)


class OpenDrawer(DrawerCabinetTask):
    name = "open_drawer"

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        color = self.place_cabinet(model, data, rng, opening=0.0)
        return str(rng.choice(_TEMPLATES)).format(color=color)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self.opening(data) >= SUCCESS_OPENING

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        reach = np.exp(-10 * np.linalg.norm(eef_pos - self.slot_point(data)))
        return float(0.3 * reach + 0.65 * min(self.opening(data) / SUCCESS_OPENING, 1.0))

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        yaw = self.cabinet_yaw(data)  # fingers close across the bar, so the finger block is thin along the pull
        out = self.outward(data)
        slot = self.slot_point(data)
        pulled = slot + out * (_PULL_TO - self.opening(data))

        def hooked() -> bool:
            offset = data.site(self._pinch).xpos - self.slot_point(data)
            along = offset @ out
            return bool(abs(along) < 0.025 and np.linalg.norm(offset[:2] - along * out[:2]) < 0.04 and offset[2] < 0.01)

        return [
            Waypoint(slot + [0, 0, 0.08], closure=1.0, yaw=yaw, tolerance=0.015),
            Waypoint(lambda: self.slot_point(data), closure=1.0, yaw=yaw, tolerance=0.006, speed=0.5),
            Waypoint(pulled, closure=1.0, yaw=yaw, tolerance=0.01, speed=0.5, requires=hooked),
        ]
