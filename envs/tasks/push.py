"""Push: slide the named puck into a marked goal square with the closed gripper, without grasping."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from ..robot import RobotConfig
from ..scene import add_free_cylinder, add_marker
from .base import COLORS, Task, sample_separated, set_free_body_pose
from .fixtures import local_xyz, set_mocap_pose

PUCK_RADIUS = 0.03
PUCK_HALF_HEIGHT = 0.015
GOAL_HALF = 0.05
PUCKS = ("target_puck", "distractor_puck")
PUSH_HEIGHT = 0.02  # pinch height while pushing: fingertips just above the table
FINGER_REACH = 0.011  # closed fingertips extend this far from the pinch along the push direction
CONTACT_DISTANCE = PUCK_RADIUS + FINGER_REACH  # pinch-to-puck-centre distance when touching
PUSH_LEAD = 0.03  # how far ahead of the contact point the pusher aims each step
_TEMPLATES = (
    "push the {color} puck into the marked square",
    "slide the {color} puck onto the goal area",
    "push the {color} puck to the target square without grasping it",
)
_AREA = (np.array([0.38, -0.22]), np.array([0.6, 0.22]))
_PUSH_DISTANCE = (0.12, 0.22)  # puck start to goal centre


class Push(Task):
    name = "push"
    category = "other"
    max_episode_steps = 200
    environment_state_dim = 9  # target puck xyz, distractor puck xyz, goal xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        for puck in PUCKS:
            add_free_cylinder(spec, puck, PUCK_RADIUS, PUCK_HALF_HEIGHT)
        add_marker(spec, "goal", (GOAL_HALF, GOAL_HALF), rgba=(0.95, 0.95, 0.92, 1))

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._pinch = robot.end_effectors[0].site

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        goal_xy, puck_xy, distractor_xy = self._layout(rng)
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_puck").rgba = COLORS[target]
        model.geom("distractor_puck").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_puck", np.r_[puck_xy, PUCK_HALF_HEIGHT])
        set_free_body_pose(data, "distractor_puck", np.r_[distractor_xy, PUCK_HALF_HEIGHT])
        set_mocap_pose(model, data, "goal", goal_xy, rng.uniform(-np.pi / 4, np.pi / 4))
        return str(rng.choice(_TEMPLATES)).format(color=target)

    @staticmethod
    def _layout(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Goal, puck and distractor positions: the push path and the pusher's approach stay clear."""
        for _ in range(1000):
            goal_xy, puck_xy = sample_separated(rng, 2, *_AREA, min_distance=_PUSH_DISTANCE[0])
            path = goal_xy - puck_xy
            if np.linalg.norm(path) > _PUSH_DISTANCE[1]:
                continue
            approach = puck_xy - path / np.linalg.norm(path) * (CONTACT_DISTANCE + 0.05)
            distractor_xy = rng.uniform(*_AREA)
            if _segment_distance(distractor_xy, approach, goal_xy) > 0.12:
                return goal_xy, puck_xy, distractor_xy
        raise RuntimeError("could not lay out the pucks and goal")

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        local = local_xyz(data, "goal", "target_puck")
        # On the table: a puck carried over the square does not count.
        return bool(np.all(np.abs(local[:2]) < GOAL_HALF) and local[2] < PUCK_HALF_HEIGHT + 0.005)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        puck, goal = data.body("target_puck").xpos, data.body("goal").xpos
        direction = _unit(goal[:2] - puck[:2])
        behind = np.r_[puck[:2] - direction * CONTACT_DISTANCE, PUSH_HEIGHT]
        reach = np.exp(-10 * np.linalg.norm(eef_pos - behind))
        push = np.exp(-10 * max(np.linalg.norm(goal[:2] - puck[:2]) - GOAL_HALF, 0.0))
        return float(0.3 * reach + 0.65 * push)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body(b).xpos for b in (*PUCKS, "goal")])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        puck, goal, pinch = data.body("target_puck"), data.body("goal"), data.site(self._pinch)

        def direction() -> np.ndarray:
            return _unit(goal.xpos[:2] - puck.xpos[:2])

        def behind(clearance: float, height: float) -> np.ndarray:
            return np.r_[puck.xpos[:2] - direction() * (CONTACT_DISTANCE + clearance), height]

        def in_contact_line() -> bool:
            """Pusher still behind the puck and facing the goal; otherwise lift and re-approach."""
            offset = puck.xpos[:2] - pinch.xpos[:2]
            along = offset @ direction()
            across = abs(offset[0] * direction()[1] - offset[1] * direction()[0])
            return bool(along > FINGER_REACH and across < 0.6 * PUCK_RADIUS and pinch.xpos[2] < 2 * PUSH_HEIGHT)

        yaw = float(np.arctan2(*direction()[::-1]))  # fingers' wide side faces the push direction
        return [
            Waypoint(lambda: behind(0.03, 0.1), closure=1.0, yaw=yaw, tolerance=0.02),
            Waypoint(lambda: behind(0.02, PUSH_HEIGHT), closure=1.0, yaw=yaw, tolerance=0.008, speed=0.6),
            # Aim just past the contact point: the puck moves, the target follows it to the goal.
            Waypoint(lambda: behind(-PUSH_LEAD, PUSH_HEIGHT), closure=1.0, yaw=yaw, tolerance=0.0,
                     speed=0.4, requires=in_contact_line),
        ]


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / max(np.linalg.norm(vector), 1e-9)


def _segment_distance(point: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
    """Distance from ``point`` to the segment ``start``-``end``."""
    t = np.clip((point - start) @ (end - start) / ((end - start) @ (end - start)), 0.0, 1.0)
    return float(np.linalg.norm(point - (start + t * (end - start))))
