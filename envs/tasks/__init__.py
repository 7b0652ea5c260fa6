"""Task registry: one task per module, looked up by robot suite and name."""

from __future__ import annotations

from .base import CATEGORIES, Task
from .close_drawer import CloseDrawer
from .humanoid import HUMANOID_TASKS
from .open_drawer import OpenDrawer
from .peg_insert import PegInsert
from .pick_into_bin import PickIntoBin
from .pick_place import PickPlace
from .press_button import PressButton
from .push import Push
from .stack import Stack

_TASKS: dict[str, dict[str, type[Task]]] = {}


def register_task(cls: type[Task]) -> type[Task]:
    """Add a task class to its robot's suite."""
    if cls.category not in CATEGORIES:
        raise ValueError(f"task {cls.name!r} has unknown category {cls.category!r}; expected one of {CATEGORIES}")
    _TASKS.setdefault(cls.robot, {})[cls.name] = cls
    return cls


for _cls in (PickPlace, PickIntoBin, OpenDrawer, CloseDrawer, Stack, Push, PressButton, PegInsert,
              *HUMANOID_TASKS):
    register_task(_cls)


def list_tasks(robot: str = "franka") -> list[str]:
    """Names of the tasks in a robot's suite."""
    if robot not in _TASKS:
        raise ValueError(f"unknown robot {robot!r}; expected one of {sorted(_TASKS)}")
    return sorted(_TASKS[robot])


def make_task(name: str, robot: str = "franka") -> Task:
    """A fresh task instance; unknown names raise ``ValueError`` listing the suite."""
    suite = list_tasks(robot)
    if name not in suite:
        raise ValueError(f"unknown {robot} task {name!r}; available: {suite}")
    return _TASKS[robot][name]()
