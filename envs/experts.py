"""Scripted experts: closed-loop waypoint followers in the env's action space.

A task plans a list of steps from the current state; a step holds one
:class:`Waypoint` per end effector (a bare waypoint for one-armed robots).
The expert turns the current step into a bounded delta action per end
effector (translation, rotation toward the end effector's grasp orientation
at the waypoint's yaw, closure) and moves on once every end effector has
reached its waypoint, so two hands stay in step (a hand-over waits for the
receiving hand). A waypoint's position may be a callable, re-read every
step, which makes pushing and tracking closed-loop. If a waypoint's
``requires`` condition fails (a dropped object) or a step stalls, the expert
replans from scratch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from .robot import EndEffector

Vector = np.ndarray | Callable[[], np.ndarray]
Pose = tuple[np.ndarray, np.ndarray]  # position, rotation matrix
_ROTATION_TOLERANCE = 0.15  # rad: a waypoint also needs the orientation this close to count as reached


@dataclasses.dataclass
class Waypoint:
    """One end effector's target in a scripted motion.

    Attributes:
        position: end-effector site target in world coordinates, or a callable giving it.
        closure: gripper/hand command, 0 open to 1 closed.
        yaw: turn of the end effector's grasp orientation about world z.
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


Step = Waypoint | Sequence[Waypoint]


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector that rotates ``current`` onto ``target``."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, (target @ current.T).ravel())
    axis_angle = np.empty(3)
    mujoco.mju_quat2Vel(axis_angle, quat, 1.0)
    return axis_angle


def equivalent_yaw(yaw: float, near: float, period: float = np.pi / 2) -> float:
    """The yaw equivalent to ``yaw`` under a ``period`` symmetry (a grasp's, a square's) that is nearest ``near``."""
    return float(yaw + period * np.round((near - yaw) / period))


class WaypointExpert:
    """Follows a task's plan with bounded delta actions, for any number of end effectors.

    Args:
        plan: returns the steps from the current state (called at reset and on replans).
        end_effectors: the robot's end effectors, in action order.
        poses: returns each end effector's measured (position, rotation matrix).
        max_translation: metres per unit of action (the env's delta scale).
        max_rotation: radians per unit of action.
        stall_steps: control steps on one step before replanning.
    """

    def __init__(self, plan: Callable[[], list[Step]], end_effectors: Sequence[EndEffector],
                 poses: Callable[[], Sequence[Pose]], max_translation: float, max_rotation: float,
                 stall_steps: int = 80) -> None:
        self._plan = plan
        self.end_effectors = tuple(end_effectors)
        self._poses = poses
        self.max_translation = max_translation
        self.max_rotation = max_rotation
        self.stall_steps = stall_steps
        self.reset()

    def reset(self) -> None:
        self.steps = [self._as_step(step) for step in self._plan()]
        self.index = 0
        self._held = 0
        self._steps_on_step = 0

    def act(self) -> np.ndarray:
        """Action for the current state: 7 numbers per end effector."""
        step = self.steps[min(self.index, len(self.steps) - 1)]
        if self._should_replan(step):
            self.reset()
            step = self.steps[0]
        actions, reached = [], True
        for ee, waypoint, (pos, rot) in zip(self.end_effectors, step, self._poses(), strict=True):
            action, hand_reached = self._end_effector_action(ee, waypoint, pos, rot)
            actions.append(action)
            reached &= hand_reached
        self._advance(step, reached)
        return np.concatenate(actions).astype(np.float32)

    def _as_step(self, step: Step) -> tuple[Waypoint, ...]:
        step = (step,) if isinstance(step, Waypoint) else tuple(step)
        if len(step) != len(self.end_effectors):
            raise ValueError(f"a plan step has {len(step)} waypoints for {len(self.end_effectors)} end effectors")
        return step

    def _end_effector_action(self, ee: EndEffector, waypoint: Waypoint, pos: np.ndarray,
                             rot: np.ndarray) -> tuple[np.ndarray, bool]:
        yaw = equivalent_yaw(waypoint.yaw, ee.yaw_of(rot), ee.yaw_period)
        error = waypoint.target() - pos
        rot_error = rotation_error(ee.grasp_frame(yaw), rot)
        reached = bool(np.linalg.norm(error) < waypoint.tolerance and np.linalg.norm(rot_error) < _ROTATION_TOLERANCE)
        move = error / self.max_translation
        move *= min(1.0, waypoint.speed / max(np.abs(move).max(), 1e-9))
        turn = np.clip(rot_error / self.max_rotation, -1, 1)
        return np.concatenate([move, turn, [2 * waypoint.closure - 1]]), reached

    def _should_replan(self, step: tuple[Waypoint, ...]) -> bool:
        failed = any(w.requires is not None and not w.requires() for w in step)
        return failed or self._steps_on_step > self.stall_steps

    def _advance(self, step: tuple[Waypoint, ...], reached: bool) -> None:
        self._steps_on_step += 1
        if not reached or self.index >= len(self.steps) - 1:
            return
        self._held += 1
        if self._held > max(w.hold for w in step):
            self.index += 1
            self._held = 0
            self._steps_on_step = 0
