"""Scripted experts: closed-loop waypoint followers in the env's action space.

A task plans a list of :class:`Waypoint` from the current state; the expert
turns the next unmet waypoint into a bounded delta action (translation,
rotation toward a top-down grasp with a given yaw, gripper closure). A
waypoint's position may be a callable, re-read every step, which makes
pushing and tracking closed-loop. If a waypoint's ``requires`` condition
fails (a dropped object) or it stalls, the expert replans from scratch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import mujoco
import numpy as np

Vector = np.ndarray | Callable[[], np.ndarray]

# Gripper pointing straight down, fingers closing along world y, at yaw 0.
_TOP_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


@dataclasses.dataclass
class Waypoint:
    """One target of a scripted motion.

    Attributes:
        position: end-effector (pinch) target in world coordinates, or a callable giving it.
        closure: gripper command, 0 open to 1 closed.
        yaw: gripper rotation about world z for a top-down grasp.
        tolerance: position error (m) below which the waypoint counts as reached.
        hold: control steps to keep commanding it after it is reached (e.g. let fingers close).
        speed: fraction of the maximum translation per step.
        requires: condition that must hold while this waypoint runs, else replan.
    """

    position: Vector
    closure: float
    yaw: float = 0.0
    tolerance: float = 0.01
    hold: int = 0
    speed: float = 1.0
    requires: Callable[[], bool] | None = None

    def target(self) -> np.ndarray:
        return np.asarray(self.position() if callable(self.position) else self.position, dtype=float)


def top_down_rotation(yaw: float) -> np.ndarray:
    """Rotation matrix of a downward-pointing gripper rotated by ``yaw`` about world z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ _TOP_DOWN


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector that rotates ``current`` onto ``target``."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, (target @ current.T).ravel())
    axis_angle = np.empty(3)
    mujoco.mju_quat2Vel(axis_angle, quat, 1.0)
    return axis_angle


def equivalent_yaw(yaw: float, current_yaw: float) -> float:
    """The parallel-gripper yaw (period pi) nearest the current one, to avoid needless turns."""
    return yaw + np.pi * np.round((current_yaw - yaw) / np.pi)


class WaypointExpert:
    """Follows a task's waypoint plan with bounded delta actions.

    Args:
        plan: returns the waypoints from the current state (called at reset and on replans).
        max_translation: metres per unit of action (the env's delta scale).
        max_rotation: radians per unit of action.
        stall_steps: steps on one waypoint before replanning.
    """

    def __init__(self, plan: Callable[[], list[Waypoint]], max_translation: float, max_rotation: float,
                 stall_steps: int = 80) -> None:
        self._plan = plan
        self.max_translation = max_translation
        self.max_rotation = max_rotation
        self.stall_steps = stall_steps
        self.reset()

    def reset(self) -> None:
        self.waypoints = self._plan()
        self.index = 0
        self._held = 0
        self._steps_on_waypoint = 0

    def act(self, eef_pos: np.ndarray, eef_rot: np.ndarray) -> np.ndarray:
        """Action for the current end-effector position and rotation matrix."""
        waypoint = self.waypoints[min(self.index, len(self.waypoints) - 1)]
        if self._should_replan(waypoint):
            self.reset()
            waypoint = self.waypoints[0]
        current_yaw = float(np.arctan2(eef_rot[1, 0], eef_rot[0, 0]))
        error = waypoint.target() - eef_pos
        rot_error = rotation_error(top_down_rotation(equivalent_yaw(waypoint.yaw, current_yaw)), eef_rot)
        self._advance(waypoint, np.linalg.norm(error) < waypoint.tolerance and np.linalg.norm(rot_error) < 0.15)
        step = error / self.max_translation
        step *= min(1.0, waypoint.speed / max(np.abs(step).max(), 1e-9))
        action = np.concatenate([step, np.clip(rot_error / self.max_rotation, -1, 1), [2 * waypoint.closure - 1]])
        return action.astype(np.float32)

    def _should_replan(self, waypoint: Waypoint) -> bool:
        failed = waypoint.requires is not None and not waypoint.requires()
        return failed or self._steps_on_waypoint > self.stall_steps

    def _advance(self, waypoint: Waypoint, reached: bool) -> None:
        self._steps_on_waypoint += 1
        if not reached or self.index >= len(self.waypoints) - 1:
            return
        self._held += 1
        if self._held > waypoint.hold:
            self.index += 1
            self._held = 0
            self._steps_on_waypoint = 0
