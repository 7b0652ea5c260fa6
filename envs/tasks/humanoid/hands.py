"""What the humanoid tasks share: which hand acts, where the idle hand waits, side grasps.

The G1's two hands are end effectors 0 (left) and 1 (right); a plan step
holds one waypoint per hand. One-handed motions use the hand on the
object's side of the table while the other hand waits out of its way.
Both palms face the midline at yaw 0 (the side grasp), so a hand closes
around an object from the object's outer side.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import mink
import mujoco
import numpy as np

from ...experts import Step, Vector, Waypoint
from ...g1 import SIDES
from ...robot import RobotConfig
from ..base import Task, geoms_touch
from ..grasping import pick_and_place

LEFT, RIGHT = 0, 1
HAND_NAMES = SIDES  # ("left", "right"), in end-effector order
APPROACH = np.array([0.0, 0.0, 0.12])  # a hand comes down onto its grasp from this far above
# Where the left hand waits while the right one works (mirrored for the right hand): outward and
# above the objects, so a hand reaching across the middle does not run into it.
_PARKED = np.array([-0.02, 0.28, 0.2])


def hand_for(position: np.ndarray) -> int:
    """The hand on the side of the table where ``position`` lies (left: y >= 0)."""
    return LEFT if position[1] >= 0 else RIGHT


def side_area(side: float, x_range: tuple[float, float],
              y_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the table area with x in ``x_range`` and ``side * y`` in ``y_range`` (side +1: left)."""
    ys = sorted((side * y_range[0], side * y_range[1]))
    return np.array([x_range[0], ys[0]]), np.array([x_range[1], ys[1]])


def park(hand: int) -> Waypoint:
    """The open ``hand`` waiting at its parking spot; never holds up a step."""
    return Waypoint(_PARKED * [1.0, 1.0 if hand == LEFT else -1.0, 1.0], closure=0.0, tolerance=np.inf)


def one_handed(waypoints: Sequence[Waypoint], hand: int) -> list[tuple[Waypoint, Waypoint]]:
    """Plan steps in which ``hand`` follows ``waypoints`` and the other hand waits parked."""
    idle = park(1 - hand)
    return [(w, idle) if hand == LEFT else (idle, w) for w in waypoints]


def beside(hand: int, yaw: float, outward: float = 0.015, back: float = 0.01) -> np.ndarray:
    """Offset of an open hand that clears an object at its grasp point.

    The hand stands off the object's side (away from the palm) and a little back,
    so the open thumb, which sticks out of the palm just behind the grasp point,
    passes behind the object even when the object leans.
    """
    sign = 1.0 if hand == LEFT else -1.0  # the left palm faces -y at yaw 0
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([-back, sign * outward])
    return np.array([c * local[0] - s * local[1], s * local[0] + c * local[1], 0.0])


def side_grasp(data: mujoco.MjData, body: str, site: str, hand: int,
               in_hand: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0,
               approach: float = APPROACH[2]) -> list[Waypoint]:
    """Lower the open hand beside ``body`` from ``approach`` above, move in and close at ``body + in_hand``.

    Coming down a little clear of the object keeps the open thumb behind it and the
    straight fingers beside it; closing wraps the fingers around the far side.
    """

    def grasp(offset: np.ndarray) -> Callable[[], np.ndarray]:
        return lambda: data.body(body).xpos + in_hand + offset

    clear = beside(hand, yaw)
    return [
        Waypoint(grasp(clear + [0.0, 0.0, approach]), closure=0.0, yaw=yaw, tolerance=0.02),
        Waypoint(grasp(clear), closure=0.0, yaw=yaw, tolerance=0.008, speed=0.6),
        Waypoint(grasp(np.zeros(3)), closure=0.0, yaw=yaw, tolerance=0.006, speed=0.5),
        Waypoint(grasp(np.zeros(3)), closure=1.0, yaw=yaw, hold=6, tolerance=0.02),
    ]


class HumanoidTask(Task):
    """Base of the humanoid suite: resolves the palm sites and the geoms of each hand."""

    robot = "humanoid"

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self.palms = tuple(ee.site for ee in robot.end_effectors)
        self.hand_geoms = tuple(np.array(mink.get_subtree_geom_ids(model, model.site(site).bodyid[0]))
                                for site in self.palms)

    def palm(self, data: mujoco.MjData, hand: int) -> np.ndarray:
        """World position of a hand's palm site (its grasp centre)."""
        return data.site(self.palms[hand]).xpos

    def touches(self, data: mujoco.MjData, hand: int, geoms: np.ndarray) -> bool:
        """Whether ``hand`` is in contact with any of ``geoms``."""
        return geoms_touch(data, self.hand_geoms[hand], geoms)

    def carry(self, data: mujoco.MjData, body: str, goal: Vector, **kwargs) -> list[Step]:
        """Pick ``body`` up with the hand on its side, side grasp, and release it at ``goal``.

        The motion is the suites' shared :func:`~dust_rl.envs.tasks.grasping.pick_and_place`
        (``kwargs`` go to it): the palm site is the grasp centre, so coming straight
        down onto the object puts the palm beside it, the thumb behind and the
        fingers past it.
        """
        hand = hand_for(data.body(body).xpos)
        return one_handed(pick_and_place(data, body, self.palms[hand], goal, **{"yaw": 0.0, **kwargs}), hand)
