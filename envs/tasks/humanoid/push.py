"""Humanoid push: slide the named block into the marked square with the flat of the open hand.

The open Dex3 hand makes an L: the palm pushes a face of the block while the
thumb, which sticks out of the palm, runs along the block's back and keeps it
from slipping off. The left palm faces right, so the left hand pushes blocks
toward the right half of the table and the right hand toward the left.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from ...experts import Step, Waypoint
from ...g1 import OPEN_THUMB_BEHIND, PALM_DEPTH
from ...scene import add_free_box, add_marker
from ..base import COLORS, set_free_body_pose
from .hands import APPROACH, LEFT, RIGHT, HumanoidTask, one_handed, side_area

BLOCK_HALF = (0.03, 0.03, 0.05)
GOAL_HALF = 0.05
PALM_HEIGHT = 0.055  # palm site height while pushing: the hand's lower edge clears the table
ALONG_PALM = BLOCK_HALF[0] + 0.005 - OPEN_THUMB_BEHIND  # block centre along the fingers: just ahead of the thumb
PUSH_LEAD = 0.03  # the palm aims this far into the block each step, so it keeps pushing
BLOCKS = ("target_block", "distractor_block")
_TEMPLATES = (
    "push the {color} block into the marked square",
    "slide the {color} block onto the square",
    "push the {color} block to the target area without picking it up",
)
_X_RANGE = (0.04, 0.16)
_SIDE_RANGE = (0.1, 0.2)  # side * y of the block's start: on the pushing hand's half
_PUSH_DISTANCE = (0.12, 0.2)
_DISTRACTOR_X = (0.3, 0.36)  # beyond the push paths
_YAW_RANGE = np.deg2rad(25)


class HumanoidPush(HumanoidTask):
    name = "push"
    category = "other"
    max_episode_steps = 150
    environment_state_dim = 9  # target block xyz, distractor block xyz, goal xyz

    def build(self, spec: mujoco.MjSpec) -> None:
        for block in BLOCKS:
            add_free_box(spec, block, BLOCK_HALF, mass=0.15)
        add_marker(spec, "goal", (GOAL_HALF, GOAL_HALF), rgba=(0.95, 0.95, 0.92, 1))

    def bind(self, model: mujoco.MjModel, robot) -> None:
        super().bind(model, robot)
        self._hand = LEFT

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        side = rng.choice([-1.0, 1.0])  # +1: the block starts on the left and the left hand pushes it right
        self._hand = LEFT if side > 0 else RIGHT
        block_xy = rng.uniform(*side_area(side, _X_RANGE, _SIDE_RANGE))
        block_yaw = rng.uniform(-_YAW_RANGE, _YAW_RANGE)
        # Push along the block face normal nearest the hand's palm normal (toward the other half).
        angle = block_yaw - side * np.pi / 2
        direction = np.array([np.cos(angle), np.sin(angle)])
        goal_xy = block_xy + direction * rng.uniform(*_PUSH_DISTANCE)
        distractor_xy = np.array([rng.uniform(*_DISTRACTOR_X), rng.uniform(-0.2, 0.2)])
        target, distractor = rng.choice(list(COLORS), size=2, replace=False)
        model.geom("target_block").rgba = COLORS[target]
        model.geom("distractor_block").rgba = COLORS[distractor]
        set_free_body_pose(data, "target_block", np.r_[block_xy, BLOCK_HALF[2]], block_yaw)
        set_free_body_pose(data, "distractor_block", np.r_[distractor_xy, BLOCK_HALF[2]], rng.uniform(-1, 1))
        mocap = model.body("goal").mocapid[0]
        data.mocap_pos[mocap] = np.r_[goal_xy, 0.0]
        data.mocap_quat[mocap] = (np.cos(block_yaw / 2), 0.0, 0.0, np.sin(block_yaw / 2))
        return str(rng.choice(_TEMPLATES)).format(color=target)

    def _in_goal(self, data: mujoco.MjData) -> bool:
        goal = data.body("goal")
        local = goal.xmat.reshape(3, 3).T @ (data.body("target_block").xpos - goal.xpos)
        return bool(np.all(np.abs(local[:2]) < GOAL_HALF))

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self._in_goal(data)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        block, goal = data.body("target_block").xpos, data.body("goal").xpos
        reach = np.exp(-10 * np.linalg.norm(self.palm(data, self._hand) - self._contact(data, 0.0)))
        push = np.exp(-10 * max(np.linalg.norm(goal[:2] - block[:2]) - GOAL_HALF, 0.0))
        return float(0.3 * reach + 0.65 * push)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        return np.concatenate([data.body(b).xpos for b in (*BLOCKS, "goal")])

    def _push_direction(self, data: mujoco.MjData) -> np.ndarray:
        """Unit vector from the block toward the goal (xy)."""
        offset = data.body("goal").xpos[:2] - data.body("target_block").xpos[:2]
        return offset / max(np.linalg.norm(offset), 1e-9)

    def _contact(self, data: mujoco.MjData, standoff: float, height: float = PALM_HEIGHT) -> np.ndarray:
        """Palm site target with the palm ``standoff`` behind the block's back face (negative: into it)."""
        direction = self._push_direction(data)
        fingers = np.array([-direction[1], direction[0]]) * (1.0 if self._hand == LEFT else -1.0)
        back = BLOCK_HALF[0] - PALM_DEPTH + standoff  # the palm's surface lies behind its site
        xy = data.body("target_block").xpos[:2] - direction * back - fingers * ALONG_PALM
        return np.r_[xy, height]

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Step]:
        hand, palm = self._hand, data.site(self.palms[self._hand])
        direction = self._push_direction(data)
        # Palm normal along the push: the left palm faces -y at yaw 0, the right +y.
        yaw = float(np.arctan2(direction[1], direction[0]) + (np.pi / 2 if hand == LEFT else -np.pi / 2))

        def target(standoff: float, height: float = PALM_HEIGHT) -> Callable[[], np.ndarray]:
            return lambda: self._contact(data, standoff, height)

        def in_line() -> bool:
            """The palm is still behind the block, squarely: otherwise back off and line up again."""
            offset = palm.xpos - self._contact(data, 0.0)
            along = offset[:2] @ self._push_direction(data)
            across = np.linalg.norm(offset[:2] - along * self._push_direction(data))
            return bool(-0.05 < along < 0.03 and across < 0.02)

        waypoints = [
            Waypoint(target(0.03, PALM_HEIGHT + APPROACH[2]), closure=0.0, yaw=yaw, tolerance=0.02),
            Waypoint(target(0.03), closure=0.0, yaw=yaw, tolerance=0.008, speed=0.6),
            Waypoint(target(-PUSH_LEAD), closure=0.0, yaw=yaw, tolerance=0.0, speed=0.4, requires=in_line),
        ]
        return one_handed(waypoints, hand)
