"""Press button: push down the named one of three coloured push buttons."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from ..robot import RobotConfig
from ..scene import GEOM
from .base import COLORS, Task, sample_separated

N_BUTTONS = 3  # button0 is the one the instruction names; the others are distractors
BASE_RADIUS, BASE_HEIGHT = 0.045, 0.03
CAP_RADIUS, CAP_HALF_HEIGHT = 0.03, 0.012
CAP_REST_Z = BASE_HEIGHT + 0.005  # cap centre when released
CAP_TOP = CAP_REST_Z + CAP_HALF_HEIGHT
TRAVEL = 0.012
PRESS_DEPTH = 0.008  # depression that counts as a press
# The spring's rest point sits above the travel's upper stop, so the cap rests preloaded against it
# (gravity cannot sag it) and springs back when released.
_SPRING_PRELOAD = 0.01
_FINGERTIP_BELOW_PINCH = 0.009  # the closed Panda fingertips end this far below the pinch site
_BASE_RGBA = (0.2, 0.2, 0.22, 1.0)
_AREA = (np.array([0.36, -0.22]), np.array([0.62, 0.22]))
_TEMPLATES = (
    "press the {color} button",
    "push the {color} button",
    "push down the {color} button",
)


class PressButton(Task):
    name = "press_button"
    category = "other"
    max_episode_steps = 100
    environment_state_dim = 4 * N_BUTTONS  # per button (named one first): base xyz, cap depression

    def build(self, spec: mujoco.MjSpec) -> None:
        for i in range(N_BUTTONS):
            base = spec.worldbody.add_body(name=f"button{i}", mocap=True)
            base.add_geom(name=f"button{i}_base", type=GEOM.mjGEOM_CYLINDER, size=(BASE_RADIUS, BASE_HEIGHT / 2, 0),
                          pos=(0, 0, BASE_HEIGHT / 2), rgba=_BASE_RGBA)
            cap = base.add_body(name=f"button{i}_cap", pos=(0, 0, CAP_REST_Z))
            cap.add_joint(name=f"button{i}_press", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=(0, 0, -1),
                          range=(0, TRAVEL), stiffness=200.0, springref=-_SPRING_PRELOAD, damping=2.0,
                          solref_limit=(0.005, 1.0))
            cap.add_geom(name=f"button{i}_cap", type=GEOM.mjGEOM_CYLINDER, size=(CAP_RADIUS, CAP_HALF_HEIGHT, 0),
                         mass=0.02)
            # The cap sinks into its base; only the slide joint should constrain it.
            spec.add_exclude(bodyname1=f"button{i}", bodyname2=f"button{i}_cap")

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._mocap = np.array([model.body(f"button{i}").mocapid[0] for i in range(N_BUTTONS)])
        self._press = np.array([model.joint(f"button{i}_press").qposadr[0] for i in range(N_BUTTONS)])
        self._caps = np.array([model.geom(f"button{i}_cap").id for i in range(N_BUTTONS)])

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        positions = sample_separated(rng, N_BUTTONS, *_AREA, min_distance=0.13)
        colors = rng.choice(list(COLORS), size=N_BUTTONS, replace=False)
        for i, (xy, color) in enumerate(zip(positions, colors)):
            data.mocap_pos[self._mocap[i]] = (*xy, 0.0)
            model.geom_rgba[self._caps[i]] = COLORS[color]
        return str(rng.choice(_TEMPLATES)).format(color=colors[0])

    def _depression(self, data: mujoco.MjData) -> np.ndarray:
        """How far each cap is pushed in (m), in button order."""
        return data.qpos[self._press]

    def _target_top(self, data: mujoco.MjData) -> np.ndarray:
        """Centre of the named cap's top face when released."""
        return data.mocap_pos[self._mocap[0]] + [0, 0, CAP_TOP]

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return bool(self._depression(data)[0] >= PRESS_DEPTH)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        reach = np.exp(-10 * np.linalg.norm(eef_pos - self._target_top(data)))
        pressed = np.clip(self._depression(data)[0] / PRESS_DEPTH, 0.0, 1.0)
        return float(0.5 * reach + 0.45 * pressed)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.column_stack([data.mocap_pos[self._mocap], self._depression(data)]).ravel()

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        top = self._target_top(data)
        # Aim the fingertips below the travel's bottom stop so the press is firm, not a graze.
        press = top + [0, 0, _FINGERTIP_BELOW_PINCH - TRAVEL - 0.005]
        return [
            Waypoint(top + [0, 0, 0.08], closure=1.0, tolerance=0.015),
            Waypoint(press, closure=1.0, tolerance=0.005, speed=0.5),
        ]
