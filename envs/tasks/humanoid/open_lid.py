"""Open lid: lift the lid off the pot by its upright handle and set it down on the table."""

from __future__ import annotations

import mujoco
import numpy as np

from ...experts import Step
from ...scene import GEOM, add_open_box
from ..base import COLORS, geoms_touch, set_free_body_pose
from .hands import HumanoidTask, hand_for

POT_HALF = 0.08  # outer half width of the square pot
POT_HEIGHT = 0.07
POT_WALL = 0.008
LID_HALF = 0.09  # the lid's plate overhangs the walls
LID_THICKNESS = 0.012
PLUG_HALF = (POT_HALF - POT_WALL - 0.003, 0.008)  # under the plate, inside the walls: the lid cannot slide off
HANDLE_RADIUS = 0.02
HANDLE_HALF_HEIGHT = 0.05  # tall enough for the hand to close around it above the plate
GRASP_ABOVE_CENTRE = 0.008  # palm site above the handle's centre: the lower finger clears the plate
SET_DOWN_OFFSET = 0.22  # the lid goes down this far to the acting hand's side of the pot
_PLATE_BOTTOM = 2 * PLUG_HALF[1]  # lid frame: the plug's bottom is at z = 0, so a lid on the table is at z = 0
_SET_DOWN_HEIGHT = 0.008  # lid height when the hand lets go of it over the table
_TEMPLATES = (
    "take the lid off the {color} pot",
    "open the {color} pot",
    "remove the lid from the {color} pot and put it on the table",
)
_AREA = (np.array([0.1, -0.06]), np.array([0.17, 0.06]))
_LID_RGBA = (0.8, 0.8, 0.82, 1.0)


class OpenLid(HumanoidTask):
    name = "open_lid"
    category = "open_close"
    max_episode_steps = 200
    environment_state_dim = 6  # lid xyz, pot xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        add_open_box(spec, "pot", POT_HALF - POT_WALL, POT_WALL, POT_HEIGHT, POT_WALL)
        lid = spec.worldbody.add_body(name="lid")
        lid.add_freejoint(name="lid_joint")
        geoms = (("lid_plug", (PLUG_HALF[0], PLUG_HALF[0], PLUG_HALF[1]), PLUG_HALF[1]),
                 ("lid", (LID_HALF, LID_HALF, LID_THICKNESS / 2), _PLATE_BOTTOM + LID_THICKNESS / 2))
        for name, size, z in geoms:
            lid.add_geom(name=name, type=GEOM.mjGEOM_BOX, size=size, pos=(0, 0, z), mass=0.05, rgba=_LID_RGBA)
        lid.add_geom(name="lid_handle", type=GEOM.mjGEOM_CYLINDER, size=(HANDLE_RADIUS, HANDLE_HALF_HEIGHT, 0),
                     pos=(0, 0, self.handle_height()), mass=0.03, rgba=(0.2, 0.2, 0.22, 1),
                     friction=(1.2, 0.01, 0.001), condim=4)

    @staticmethod
    def handle_height() -> float:
        """Height of the handle's centre in the lid's frame."""
        return _PLATE_BOTTOM + LID_THICKNESS + HANDLE_HALF_HEIGHT

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._lid_geoms = np.array([model.geom(g).id for g in ("lid_plug", "lid", "lid_handle")])
        self._pot_geoms = np.array([model.geom(g).id for g in ("pot_floor", *(f"pot_wall_{i}" for i in range(4)))])

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        pot_xy = rng.uniform(*_AREA)
        color = str(rng.choice(list(COLORS)))
        model.geom_rgba[self._pot_geoms] = COLORS[color]
        data.mocap_pos[model.body("pot").mocapid[0]] = np.r_[pot_xy, 0.0]
        # The plate rests on the walls; the plug hangs inside them.
        set_free_body_pose(data, "lid", np.r_[pot_xy, POT_HEIGHT - _PLATE_BOTTOM], rng.uniform(-0.3, 0.3))
        return str(rng.choice(_TEMPLATES)).format(color=color)

    def _lid_off(self, data: mujoco.MjData) -> bool:
        lid, pot = data.body("lid").xpos, data.body("pot").xpos
        return bool(np.linalg.norm(lid[:2] - pot[:2]) > POT_HALF + LID_HALF and lid[2] < LID_THICKNESS)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._lid_off(data) and not any(self.touches(data, hand, self._lid_geoms) for hand in (0, 1))

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        lid, pot = data.body("lid").xpos, data.body("pot").xpos
        handle = lid + [0, 0, self.handle_height()]
        reach = np.exp(-10 * np.linalg.norm(self.palm(data, hand_for(lid)) - handle))
        lifted = float(lid[2] > POT_HEIGHT - _PLATE_BOTTOM + 0.02 or not self._on_pot(data))
        away = min(np.linalg.norm(lid[:2] - pot[:2]) / (POT_HALF + LID_HALF), 1.0)
        return float(0.3 * reach + 0.2 * lifted + 0.45 * away * lifted)

    def _on_pot(self, data: mujoco.MjData) -> bool:
        return geoms_touch(data, self._lid_geoms, self._pot_geoms)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body("lid").xpos, data.body("pot").xpos])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        side = 1.0 if data.body("lid").xpos[1] >= 0 else -1.0  # set down on the acting hand's side
        down = data.body("pot").xpos + [0.0, side * SET_DOWN_OFFSET, _SET_DOWN_HEIGHT]
        return self.carry(data, "lid", down, grasp_height=self.handle_height() + GRASP_ABOVE_CENTRE,
                          place_tolerance=0.015)
