"""What the environment and controller need to know about a robot.

A robot module (``franka.py``, ``g1.py``, ...) attaches its Menagerie model to
a scene spec and returns a :class:`RobotConfig`; the controller, the
environment, the scripted experts and the tasks only ever see this
description, so one code path serves every robot.
"""

from __future__ import annotations

import dataclasses

import numpy as np

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


@dataclasses.dataclass(frozen=True)
class EndEffector:
    """One controlled end effector: a site that mink tracks and its closure actuators.

    Attributes:
        site: name of the site whose pose the policy commands.
        actuators: actuators driven by the closure command (gripper or hand).
        open_ctrl: actuator controls for a fully open gripper/hand.
        closed_ctrl: actuator controls for a fully closed gripper/hand.
        opening_joints: the gripper/hand joints, reported in the state.
        grasp_rotation: site orientation (world frame) of this end effector's grasp at yaw 0,
            e.g. a gripper pointing down or a palm facing the object's side; scripted experts
            turn it about world z.
        yaw_period: turn about world z after which the grasp repeats (pi for a parallel
            gripper, 2 pi for a hand).
        opening_weights: weights of `opening_joints` in the scalar opening measure
            (larger = more open); None sums them (the Panda's finger separation).
    """

    site: str
    actuators: tuple[str, ...]
    open_ctrl: tuple[float, ...]
    closed_ctrl: tuple[float, ...]
    opening_joints: tuple[str, ...]
    grasp_rotation: Matrix3
    yaw_period: float = 2 * np.pi
    opening_weights: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        # Arrays once, not per control step (frozen dataclass, hence object.__setattr__).
        object.__setattr__(self, "_open", np.asarray(self.open_ctrl, dtype=float))
        object.__setattr__(self, "_span", np.asarray(self.closed_ctrl, dtype=float) - self._open)

    def closure_to_ctrl(self, closure: float) -> np.ndarray:
        """Map a closure in [0, 1] (0 open, 1 closed) to actuator controls (a grasp synergy)."""
        return self._open + closure * self._span

    def opening(self, joint_positions: np.ndarray) -> float:
        """Scalar opening from the positions of ``opening_joints``."""
        if self.opening_weights is None:
            return float(np.sum(joint_positions))
        return float(np.dot(self.opening_weights, joint_positions))

    def grasp_frame(self, yaw: float) -> np.ndarray:
        """Rotation matrix of the grasp orientation turned by ``yaw`` about world z."""
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.asarray(self.grasp_rotation)

    def yaw_of(self, rotation: np.ndarray) -> float:
        """The yaw (about world z) that best explains a measured site rotation."""
        relative = rotation @ np.asarray(self.grasp_rotation).T
        return float(np.arctan2(relative[1, 0], relative[0, 0]))


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """A robot placed in a scene.

    Attributes:
        name: robot suite name used in registration (`"franka"`, `"humanoid"`).
        arm_joints: joints driven through inverse kinematics, in actuator order.
        arm_actuators: position actuators that receive the IK joint targets.
        end_effectors: controlled end effectors, in action order.
        home_qpos: joint name -> home position, also the IK posture target.
        cameras: camera names this robot brings (e.g. `("wrist",)`).
        default_cameras: cameras observed when the user names none (scene or robot cameras).
        max_joint_velocity: joint name -> velocity limit (rad/s) used by IK.
        workspace: (low, high) corners of the absolute-mode position box, table frame (m).
        collision_pairs: pairs of geom-name groups that the IK keeps apart
            (`mink.CollisionAvoidanceLimit`); empty for none.
        posture_costs: joint name -> IK posture weight where it differs from the controller's default.
    """

    name: str
    arm_joints: tuple[str, ...]
    arm_actuators: tuple[str, ...]
    end_effectors: tuple[EndEffector, ...]
    home_qpos: dict[str, float]
    cameras: tuple[str, ...]
    default_cameras: tuple[str, ...]
    max_joint_velocity: dict[str, float]
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]]
    collision_pairs: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = ()
    posture_costs: dict[str, float] = dataclasses.field(default_factory=dict)
