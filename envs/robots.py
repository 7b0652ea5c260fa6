"""Robot suite name -> function that attaches the robot to a scene spec."""

from __future__ import annotations

from collections.abc import Callable

import mujoco

from .franka import add_franka
from .g1 import add_g1
from .robot import RobotConfig

ROBOT_BUILDERS: dict[str, Callable[[mujoco.MjSpec], RobotConfig]] = {"franka": add_franka, "humanoid": add_g1}
