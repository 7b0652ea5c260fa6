"""What the environment and controller need to know about a robot.

A robot module (``franka.py``, ...) attaches its Menagerie model to a scene
spec and returns a :class:`RobotConfig`; the controller, the environment and
the tasks only ever see this description, so one code path serves every
robot.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class EndEffector:
    """One controlled end effector: a site that mink tracks and its closure actuators.

    Attributes:
        site: name of the site whose pose the policy commands.
        actuators: actuators driven by the closure command (gripper or hand).
        open_ctrl: actuator controls for a fully open gripper/hand.
        closed_ctrl: actuator controls for a fully closed gripper/hand.
        opening_joints: joints whose summed position measures the opening.
    """

    site: str
    actuators: tuple[str, ...]
    open_ctrl: tuple[float, ...]
    closed_ctrl: tuple[float, ...]
    opening_joints: tuple[str, ...]

    def closure_to_ctrl(self, closure: float) -> np.ndarray:
        """Map a closure in [0, 1] (0 open, 1 closed) to actuator controls (a grasp synergy)."""
        lo, hi = np.asarray(self.open_ctrl), np.asarray(self.closed_ctrl)
        return lo + closure * (hi - lo)


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """A robot placed in a scene.

    Attributes:
        name: short robot name used in registration (``"franka"``).
        arm_joints: joints driven through inverse kinematics, in actuator order.
        arm_actuators: position actuators that receive the IK joint targets.
        end_effectors: controlled end effectors, in action order.
        home_qpos: joint name -> home position, also the IK posture target.
        cameras: camera names this robot brings (e.g. ``("wrist",)``).
        max_joint_velocity: joint name -> velocity limit (rad/s) used by IK.
    """

    name: str
    arm_joints: tuple[str, ...]
    arm_actuators: tuple[str, ...]
    end_effectors: tuple[EndEffector, ...]
    home_qpos: dict[str, float]
    cameras: tuple[str, ...]
    max_joint_velocity: dict[str, float]
