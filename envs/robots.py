"""Robot name -> function that attaches the robot to a scene spec."""

from __future__ import annotations

from collections.abc import Callable

import mujoco

from .franka import add_franka
from .robot import RobotConfig

ROBOT_BUILDERS: dict[str, Callable[[mujoco.MjSpec], RobotConfig]] = {"franka": add_franka}
