"""A one-drawer cabinet fixture shared by the drawer tasks.

The cabinet is a static mocap body, so reset can move and turn it without a
free joint; its drawer slides out toward the robot on a damped slide joint
and carries a bar handle on stand-offs. The handle sits high on the drawer
front, and stands far enough off it, that a closed top-down gripper can drop
its fingers into the slot behind the bar without the hand touching the
cabinet; from there it pulls the bar or pushes the drawer front.
"""

from __future__ import annotations

import mink
import mujoco
import numpy as np

from ..robot import RobotConfig
from ..scene import GEOM
from .base import COLORS, Task

DEPTH, WIDTH, HEIGHT = 0.20, 0.24, 0.12  # outer size of the housing
WALL = 0.01
GAP = 0.003  # clearance between drawer and housing
MAX_OPENING = 0.16
HANDLE_STANDOFF = 0.06  # bar axis in front of the drawer front
HANDLE_RADIUS = 0.007
HANDLE_HALF_LENGTH = 0.06
HANDLE_Z = 0.095  # high enough that the hand (~4 cm above the pinch) clears the housing top from the slot
_SLOT_DROP = 0.004  # fingertips in the slot reach this far below the bar's axis

_TRAY_RGBA = (0.88, 0.84, 0.74, 1.0)
_HANDLE_RGBA = (0.25, 0.25, 0.27, 1.0)
_X_RANGE = (0.55, 0.68)
_Y_RANGE = (-0.08, 0.08)
_YAW_RANGE = np.deg2rad(15.0)
_FRONT = -DEPTH / 2  # local x of the housing's front face; the drawer opens along local -x


class DrawerCabinetTask(Task):
    """Base of the drawer tasks: builds, places and reads the cabinet.

    Subclasses decide the starting opening, the instruction, success and the expert.
    """

    category = "open_close"
    max_episode_steps = 150
    environment_state_dim = 8  # handle xyz, cabinet xyz, cabinet yaw, drawer opening

    def build(self, spec: mujoco.MjSpec) -> None:
        cabinet = spec.worldbody.add_body(name="cabinet", mocap=True)
        inner_half_width = WIDTH / 2 - WALL
        for name, pos, half in (
            ("top", (0, 0, HEIGHT - WALL / 2), (DEPTH / 2, WIDTH / 2, WALL / 2)),
            ("bottom", (0, 0, WALL / 2), (DEPTH / 2, WIDTH / 2, WALL / 2)),
            ("left", (0, inner_half_width + WALL / 2, HEIGHT / 2), (DEPTH / 2, WALL / 2, HEIGHT / 2)),
            ("right", (0, -inner_half_width - WALL / 2, HEIGHT / 2), (DEPTH / 2, WALL / 2, HEIGHT / 2)),
            ("back", (DEPTH / 2 - WALL / 2, 0, HEIGHT / 2), (WALL / 2, inner_half_width, HEIGHT / 2)),
        ):
            cabinet.add_geom(name=f"cabinet_{name}", type=GEOM.mjGEOM_BOX, size=half, pos=pos)

        drawer = cabinet.add_body(name="drawer")
        # Damping and friction stop the drawer within about a centimetre once it is let go.
        drawer.add_joint(name="drawer_slide", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=(-1, 0, 0),
                         range=(0, MAX_OPENING), damping=15.0, frictionloss=0.5, armature=0.05)
        half_w = inner_half_width - GAP  # drawer box half width
        bottom_z = WALL + GAP
        front_half_h = (HEIGHT - 2 * WALL - 2 * GAP) / 2
        length = DEPTH - 2 * WALL - GAP  # front panel to back panel, outer
        box_half_h = 0.03
        center_x = _FRONT + length / 2
        for name, pos, half in (
            ("front", (_FRONT + WALL / 2, 0, bottom_z + front_half_h), (WALL / 2, half_w, front_half_h)),
            ("floor", (center_x, 0, bottom_z + WALL / 2), (length / 2, half_w, WALL / 2)),
            ("left", (center_x, half_w - WALL / 2, bottom_z + box_half_h), (length / 2, WALL / 2, box_half_h)),
            ("right", (center_x, -half_w + WALL / 2, bottom_z + box_half_h), (length / 2, WALL / 2, box_half_h)),
            ("back", (_FRONT + length - WALL / 2, 0, bottom_z + box_half_h), (WALL / 2, half_w, box_half_h)),
        ):
            drawer.add_geom(name=f"drawer_{name}", type=GEOM.mjGEOM_BOX, size=half, pos=pos, mass=0.1,
                            rgba=_TRAY_RGBA)
        bar_x = _FRONT - HANDLE_STANDOFF
        drawer.add_geom(name="drawer_handle", type=GEOM.mjGEOM_CYLINDER, size=(HANDLE_RADIUS, HANDLE_HALF_LENGTH, 0),
                        pos=(bar_x, 0, HANDLE_Z), quat=(np.sqrt(0.5), np.sqrt(0.5), 0, 0), rgba=_HANDLE_RGBA,
                        mass=0.05)
        for side in (-1, 1):
            drawer.add_geom(name=f"drawer_handle_post{side:+d}", type=GEOM.mjGEOM_BOX,
                            size=(HANDLE_STANDOFF / 2, 0.005, 0.005), rgba=_HANDLE_RGBA, mass=0.01,
                            pos=(_FRONT - HANDLE_STANDOFF / 2, side * (HANDLE_HALF_LENGTH - 0.005), HANDLE_Z))
        drawer.add_site(name="drawer_handle", pos=(bar_x, 0, HANDLE_Z), group=4)
        # The drawer rides on its joint; contacts with its own housing would only fight the slide.
        spec.add_exclude(bodyname1="cabinet", bodyname2="drawer")

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._pinch = robot.end_effectors[0].site
        self._mocap = model.body("cabinet").mocapid[0]
        self._slide = model.joint("drawer_slide").qposadr[0]
        self._slide_dof = model.joint("drawer_slide").dofadr[0]
        self._colored = [*mink.get_body_geom_ids(model, model.body("cabinet").id), model.geom("drawer_front").id]

    def place_cabinet(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator,
                      opening: float) -> str:
        """Randomise the cabinet pose and colour, set the drawer opening; returns the colour name."""
        xy = rng.uniform((_X_RANGE[0], _Y_RANGE[0]), (_X_RANGE[1], _Y_RANGE[1]))
        yaw = rng.uniform(-_YAW_RANGE, _YAW_RANGE)
        color = str(rng.choice(list(COLORS)))
        data.mocap_pos[self._mocap] = (*xy, 0.0)
        data.mocap_quat[self._mocap] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        # The front camera sees the cabinet from behind, so the housing carries the named colour too;
        # the tray stays pale so an open drawer stands out against it.
        model.geom_rgba[self._colored] = COLORS[color]
        data.qpos[self._slide] = opening
        data.qvel[self._slide_dof] = 0.0
        return color

    def opening(self, data: mujoco.MjData) -> float:
        """How far the drawer is pulled out (m)."""
        return float(data.qpos[self._slide])

    def cabinet_yaw(self, data: mujoco.MjData) -> float:
        """Rotation of the cabinet about world z; 0 faces the drawer straight at the robot."""
        quat = data.mocap_quat[self._mocap]
        return float(2 * np.arctan2(quat[3], quat[0]))

    def outward(self, data: mujoco.MjData) -> np.ndarray:
        """World unit vector along which the drawer opens (toward the robot)."""
        yaw = self.cabinet_yaw(data)
        return np.array([-np.cos(yaw), -np.sin(yaw), 0.0])

    def handle_pos(self, data: mujoco.MjData) -> np.ndarray:
        """World position of the handle bar's centre."""
        return data.site("drawer_handle").xpos.copy()

    def slot_point(self, data: mujoco.MjData) -> np.ndarray:
        """Pinch position centred in the slot between the handle bar and the drawer front.

        Closed fingers there hook the bar to pull the drawer, or press the drawer front to push it.
        """
        inward = -self.outward(data) * (HANDLE_STANDOFF + HANDLE_RADIUS) / 2
        return self.handle_pos(data) + inward - [0, 0, _SLOT_DROP]

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([self.handle_pos(data), data.mocap_pos[self._mocap],
                               [self.cabinet_yaw(data), self.opening(data)]])
