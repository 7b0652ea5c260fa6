"""Franka Emika Panda with its hand, from MuJoCo Menagerie."""

from __future__ import annotations

import mujoco
import numpy as np

from .assets import robot_xml
from .robot import EndEffector, RobotConfig

_PREFIX = "panda/"
_ARM_JOINTS = tuple(f"{_PREFIX}joint{i}" for i in range(1, 8))
_FINGER_JOINTS = (f"{_PREFIX}finger_joint1", f"{_PREFIX}finger_joint2")
_ARM_ACTUATORS = tuple(f"actuator{i}" for i in range(1, 8))
_ARM_DAMPING_SCALE = 0.3
_GRIPPER_ACTUATOR = "actuator8"
_GRIPPER_STIFFNESS_SCALE = 3.0
_HOME = (0.0, 0.2, 0.0, -2.2, 0.0, 2.4, 0.785)
# Franka's datasheet joint velocity limits (rad/s), slightly derated.
_VMAX = (2.0, 2.0, 2.0, 2.0, 2.5, 2.5, 2.5)
_COLLISION_RGBA = {"hand": (0.2, 0.2, 0.22, 1.0), "left_finger": (0.15, 0.15, 0.15, 1.0),
                   "right_finger": (0.15, 0.15, 0.15, 1.0)}
_LINK_RGBA = (0.92, 0.92, 0.94, 1.0)
# The hand pointing straight down, fingers closing along world y, at yaw 0.
_TOP_DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
# Absolute-mode position box (table frame): the reachable part of the table and above it.
_WORKSPACE = ((0.15, -0.45, 0.0), (0.85, 0.45, 0.6))


def add_franka(spec: mujoco.MjSpec, base_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RobotConfig:
    """Attach the Panda to ``spec`` with a pinch site and a wrist camera."""
    panda = mujoco.MjSpec.from_file(str(robot_xml("franka_emika_panda")))
    panda.option.integrator = spec.option.integrator
    for geom in panda.geoms:
        if geom.classname.name.startswith(("collision", "fingertip")):
            geom.rgba = _COLLISION_RGBA.get(geom.parent.name, _LINK_RGBA)
            # Collide with the world (contype 1) but not with the robot's own links:
            # self-collision costs physics time and the IK does not plan around it.
            geom.contype, geom.conaffinity = 2, 1
    # The model's own light adds to the scene's and washes colours out (orange reads as yellow).
    for light in panda.lights:
        panda.delete(light)
    for body in panda.bodies:
        body.gravcomp = 1.0
    # Menagerie's servo damping (kd = kp / 10) gives a 0.1 s lag, so the arm covers only
    # ~40% of each 50 ms command; kd = 0.03 kp tracks ~80% without overshoot.
    for actuator in panda.actuators:
        if actuator.name in _ARM_ACTUATORS:
            actuator.biasprm[2] *= _ARM_DAMPING_SCALE
        elif actuator.name == _GRIPPER_ACTUATOR:
            # Menagerie's finger servo squeezes a 4 cm cube with ~2 N, which lets it slip
            # when the arm accelerates; a stiffer servo gives ~6 N (the real hand: 70 N).
            actuator.gainprm[0] *= _GRIPPER_STIFFNESS_SCALE
            actuator.biasprm[1:3] *= _GRIPPER_STIFFNESS_SCALE
    base = spec.worldbody.add_site(name="robot_base", pos=base_pos)
    spec.attach(panda, site=base, prefix=_PREFIX)
    hand = spec.body(f"{_PREFIX}hand")
    hand.add_site(name="pinch", pos=(0, 0, 0.1034), size=(0.005, 0, 0), rgba=(1, 0, 0, 0), group=4)
    # Looks along the fingers, tilted back toward the pinch point.
    hand.add_camera(name="wrist", pos=(0.07, 0.0, 0.02), xyaxes=(0, 1, 0, 1, 0, 0.3), fovy=80)
    return RobotConfig(
        name="franka",
        arm_joints=_ARM_JOINTS,
        arm_actuators=tuple(_PREFIX + name for name in _ARM_ACTUATORS),
        end_effectors=(
            EndEffector(
                site="pinch",
                actuators=(_PREFIX + _GRIPPER_ACTUATOR,),
                open_ctrl=(255.0,),
                closed_ctrl=(0.0,),
                opening_joints=_FINGER_JOINTS,
                grasp_rotation=_TOP_DOWN,
                yaw_period=np.pi,  # the two fingers are symmetric
            ),
        ),
        home_qpos={**dict(zip(_ARM_JOINTS, _HOME)), **dict.fromkeys(_FINGER_JOINTS, 0.04)},
        cameras=("wrist",),
        default_cameras=("front", "wrist"),
        max_joint_velocity=dict(zip(_ARM_JOINTS, _VMAX)),
        workspace=_WORKSPACE,
    )
