"""The task interface: what every task adds to the scene and decides about it.

A task builds its props into the scene spec, randomises them on reset
(returning the episode's language instruction), decides success, shapes a
dense reward, exposes privileged object state, and plans its scripted
expert. Tasks are robot-agnostic where they can be; ``robot`` names the
suite a task belongs to.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np

if TYPE_CHECKING:
    from ..experts import Step
    from ..robot import RobotConfig

CATEGORIES = ("pick_and_place", "open_close", "other")

COLORS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.15, 0.15, 1.0),
    "green": (0.15, 0.7, 0.2, 1.0),
    "blue": (0.15, 0.3, 0.85, 1.0),
    "yellow": (0.9, 0.8, 0.1, 1.0),
    "purple": (0.55, 0.2, 0.7, 1.0),
    "orange": (0.95, 0.5, 0.1, 1.0),
}


class Task(abc.ABC):
    """Base class of all tasks. Subclasses set the class attributes below."""

    name: ClassVar[str]
    category: ClassVar[str]
    robot: ClassVar[str] = "franka"
    max_episode_steps: ClassVar[int] = 200
    environment_state_dim: ClassVar[int]

    @abc.abstractmethod
    def build(self, spec: mujoco.MjSpec) -> None:
        """Add this task's props to the scene spec."""

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:  # noqa: B027 (optional hook)
        """Resolve names to ids once the model is compiled (optional)."""

    @abc.abstractmethod
    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        """Randomise the props (poses, colours) and return the language instruction."""

    @abc.abstractmethod
    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        """Whether the goal holds in the current state."""

    @abc.abstractmethod
    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        """Dense shaping in [0, 1): staged distances toward the goal.

        ``eef_pos`` is the first end effector's position; tasks for several end
        effectors read the others from ``data`` through the sites bound in :meth:`bind`.
        """

    @abc.abstractmethod
    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        """Privileged object state (positions, joint values), ``environment_state_dim`` floats."""

    @abc.abstractmethod
    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        """Plan steps that solve the task from the current state (one waypoint per end effector each)."""


def set_free_body_pose(data: mujoco.MjData, body: str, pos: np.ndarray, yaw: float = 0.0) -> None:
    """Place a free body at ``pos`` rotated by ``yaw`` about z, at rest."""
    joint = data.joint(f"{body}_joint")
    joint.qpos[:3] = pos
    joint.qpos[3:] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
    joint.qvel[:] = 0.0


def body_yaw(data: mujoco.MjData, body: str) -> float:
    """Rotation of a body about world z (for grasps aligned with a box's faces)."""
    xmat = data.body(body).xmat.reshape(3, 3)
    return float(np.arctan2(xmat[1, 0], xmat[0, 0]))


QUARTER_TURN = np.pi / 2  # a square's symmetry: turns by it look the same


def yaw_features(data: mujoco.MjData, body: str, period: float = QUARTER_TURN) -> np.ndarray:
    """A body's yaw as (sin, cos) of ``2 pi / period`` times it: the same numbers for yaws its symmetry cannot tell
    apart (a cube's or a square hole's quarter turns), and no jump where an angle would wrap."""
    turn = 2 * np.pi / period * body_yaw(data, body)
    return np.array([np.sin(turn), np.cos(turn)])


def sample_separated(rng: np.random.Generator, count: int, low: np.ndarray, high: np.ndarray,
                     min_distance: float, fixed: tuple[np.ndarray, ...] = ()) -> list[np.ndarray]:
    """``count`` xy positions in a box, pairwise (and from ``fixed``) at least ``min_distance`` apart."""
    chosen: list[np.ndarray] = []
    for _ in range(10_000):
        point = rng.uniform(low, high)
        if all(np.linalg.norm(point - other) >= min_distance for other in (*fixed, *chosen)):
            chosen.append(point)
            if len(chosen) == count:
                return chosen
    raise RuntimeError(f"could not place {count} objects {min_distance} m apart in {low}..{high}")


def geoms_touch(data: mujoco.MjData, geoms_a: np.ndarray, geoms_b: np.ndarray) -> bool:
    """Whether any active contact joins a geom of ``geoms_a`` to one of ``geoms_b``."""
    g1, g2 = data.contact.geom1, data.contact.geom2
    return bool(np.any((np.isin(g1, geoms_a) & np.isin(g2, geoms_b)) | (np.isin(g2, geoms_a) & np.isin(g1, geoms_b))))
