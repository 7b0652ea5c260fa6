"""dust-rl environments: MuJoCo tabletop suites controlled through mink.

``DustEnv``, ``list_tasks`` and ``make_task`` load on first use, so that ``import dust_rl`` (which
imports :mod:`dust_rl.envs.registration` to register the gymnasium ids) stays light: the env module
pulls in MuJoCo, mink and, through :mod:`dust_rl.keys`, torch.
"""

from __future__ import annotations

import importlib
from typing import Any

from .rendering import configure_headless_gl

configure_headless_gl()

_LAZY = {"DustEnv": ".env", "list_tasks": ".tasks", "make_task": ".tasks"}

__all__ = ["DustEnv", "list_tasks", "make_task"]


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
