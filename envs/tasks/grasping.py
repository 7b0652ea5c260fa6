"""Shared scripted-expert motions: grasp an object from above, carry it and set it down.

Tasks that move one object somewhere (onto a plate, into a bin, onto a cube,
into a hole) differ only in where the object must end up, so they share one
waypoint sequence. While carrying, the targets close the loop on the object
rather than on the hand, so slip in the grasp does not spoil tight placements.
"""

from __future__ import annotations

from collections.abc import Callable

import mink
import mujoco
import numpy as np

from ..experts import Vector, Waypoint, equivalent_yaw
from ..robot import RobotConfig
from .base import body_yaw

LIFT = np.array([0.0, 0.0, 0.12])  # clearance above grasp and goal points
HOVER = np.array([0.0, 0.0, 0.04])  # where the carried object lines up before the final descent
HOLD_RADIUS = 0.03  # an object farther than this from its grasp point has been dropped
CARRY_SPEED = 0.7  # at full speed the jerk of each step slides the object along the pads


def gripper_geoms(model: mujoco.MjModel, robot: RobotConfig) -> np.ndarray:
    """Geoms of the first end effector's hand and fingers, to tell whether an object was released."""
    hand = model.site(robot.end_effectors[0].site).bodyid[0]
    return np.array(mink.get_subtree_geom_ids(model, hand))


def grasp_yaw(data: mujoco.MjData, body: str, square: bool = True) -> float:
    """Top-down grasp yaw that closes the fingers along the line from the robot base to ``body``.

    The arm wobbles in its vertical plane while it lifts and carries. With the pads facing
    along that plane the wobble presses the object against them; across it, the wobble
    twists the object about the pads' normal, where only friction holds it, and the object
    creeps out of the grasp. Of the two such yaws this is the one that turns the Panda's
    wrist toward the middle of its range (home is 2.1 rad from one end). A ``square`` body
    is grasped across its faces (the nearest such yaw); a round one at any yaw.
    """
    position = data.body(body).xpos
    radial = float(np.arctan2(position[1], position[0]) + np.pi / 2)  # the robot base is at the origin
    return equivalent_yaw(body_yaw(data, body), radial) if square else radial


def pick_and_place(data: mujoco.MjData, body: str, pinch: str, goal: Vector, yaw: float,
                   place_yaw: float | None = None, grasp_height: float = 0.0,
                   place_tolerance: float = 0.008, place_speed: float = 0.6) -> list[Waypoint]:
    """Waypoints that grasp ``body`` from above and release it with its centre at ``goal``.

    Args:
        data: current simulation state.
        body: the free body to move.
        pinch: end-effector site name.
        goal: where the body's centre should be on release; a callable is re-read every
            step (e.g. to follow another object).
        yaw: gripper yaw for the grasp (see :func:`grasp_yaw`).
        place_yaw: gripper yaw while placing (e.g. to line a peg up with a hole);
            defaults to ``yaw``.
        grasp_height: pinch height above the body's centre (tall objects are held near the top).
        place_tolerance: how close (m) the body must be to ``goal``, and first above it,
            before the fingers open.
        place_speed: fraction of the maximum speed while lowering onto the goal.
    """
    place_yaw = yaw if place_yaw is None else place_yaw
    hand = data.site(pinch).xmat.reshape(3, 3)
    # The expert turns to the nearest equivalent yaw (the gripper is symmetric under half a
    # turn); turning through the midpoint keeps it on the side of ``yaw`` that was asked for.
    turn_yaw = (float(np.arctan2(hand[1, 0], hand[0, 0])) + yaw) / 2
    in_hand = np.array([0.0, 0.0, grasp_height])
    lift_height = data.body(body).xpos[2] + grasp_height + LIFT[2]

    def grasp() -> np.ndarray:
        return data.body(body).xpos + in_hand

    def lift() -> np.ndarray:
        """Straight up from wherever the object was picked."""
        return np.r_[data.site(pinch).xpos[:2], lift_height]

    def goal_now() -> np.ndarray:
        return np.asarray(goal() if callable(goal) else goal, dtype=float)

    def holding() -> bool:
        return bool(np.linalg.norm(data.body(body).xpos + in_hand - data.site(pinch).xpos) < HOLD_RADIUS)

    def carry(offset: np.ndarray) -> Callable[[], np.ndarray]:
        """Pinch target that puts the held body at ``goal + offset``, whatever its slip in the hand."""
        return lambda: goal_now() + offset + data.site(pinch).xpos - data.body(body).xpos

    return [
        Waypoint(lambda: grasp() + LIFT, closure=0.0, yaw=turn_yaw, tolerance=0.02),
        Waypoint(lambda: grasp() + LIFT, closure=0.0, yaw=yaw, tolerance=0.02),
        Waypoint(grasp, closure=0.0, yaw=yaw, tolerance=0.006, speed=0.6),
        Waypoint(grasp, closure=1.0, yaw=yaw, hold=6, tolerance=0.02),
        Waypoint(lift, closure=1.0, yaw=yaw, tolerance=0.02, requires=holding),
        Waypoint(carry(LIFT), closure=1.0, yaw=place_yaw, tolerance=0.02, speed=CARRY_SPEED, requires=holding),
        Waypoint(carry(HOVER), closure=1.0, yaw=place_yaw, tolerance=place_tolerance, requires=holding),
        Waypoint(carry(np.zeros(3)), closure=1.0, yaw=place_yaw, tolerance=place_tolerance,
                 speed=place_speed, requires=holding),
        Waypoint(lambda: goal_now() + in_hand, closure=0.0, yaw=place_yaw, hold=4, tolerance=0.02),
        Waypoint(lambda: goal_now() + in_hand + LIFT, closure=0.0, yaw=place_yaw, tolerance=0.02),
    ]
