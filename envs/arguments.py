"""Checks of ``DustEnv``'s constructor arguments.

A wrong value must fail at construction with a ``ValueError`` naming the
argument, the value and what is allowed, instead of building a silently
different env (``image_size="64"`` once gave 6x4 images, a negative
``control_hz`` froze physics).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np

# 1 / (control_hz * physics_dt) carries four roundings (two inputs, product, quotient), each within
# half an ulp; twice that bound separates a whole number of substeps from a genuine remainder.
_SUBSTEP_RTOL = 4 * float(np.finfo(np.float64).eps)
# Largest image side an env renders: a bigger one would allocate gigabytes per frame (and per dataset row).
MAX_IMAGE_SIDE = 1024


def check_choice(name: str, value: object, choices: Sequence) -> None:
    """Raise unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; expected one of {list(choices)}")


def _is_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def image_shape(image_size: object) -> tuple[int, int, int]:
    """``(height, width, 3)`` from a positive int or a pair of positive ints, each at most ``MAX_IMAGE_SIDE``."""
    pair = image_size if isinstance(image_size, Sequence) and not isinstance(image_size, str) else None
    sizes = (image_size, image_size) if pair is None else tuple(pair)
    if len(sizes) != 2 or not all(_is_int(s) and 0 < s <= MAX_IMAGE_SIDE for s in sizes):
        raise ValueError(f"image_size must be an int in [1, {MAX_IMAGE_SIDE}] or a (height, width) pair of them, "
                         f"got {image_size!r}")
    return int(sizes[0]), int(sizes[1]), 3


def camera_names(cameras: object, available: Sequence[str]) -> tuple[str, ...]:
    """The requested cameras: a non-empty sequence of distinct names from ``available``."""
    if isinstance(cameras, str) or not isinstance(cameras, Sequence) or not cameras:
        raise ValueError(f"cameras must be a non-empty list of camera names from {list(available)}, "
                         f"got {cameras!r}")
    unknown = [c for c in cameras if c not in available]
    if unknown:
        raise ValueError(f"unknown cameras {unknown} in cameras={list(cameras)}; this scene has {list(available)}")
    if len(set(cameras)) != len(cameras):
        raise ValueError(f"cameras has duplicates: {list(cameras)}; name each camera once")
    return tuple(cameras)


def flag(name: str, value: object) -> bool:
    """A plain ``bool`` (a string such as ``"false"`` would otherwise read as true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def max_episode_steps(value: object) -> int | None:
    """A positive int, or None for the task's default."""
    if value is not None and not (_is_int(value) and value > 0):
        raise ValueError(f"max_episode_steps must be a positive int or None (the task's default), got {value!r}")
    return None if value is None else int(value)


def non_negative(name: str, value: object) -> float:
    """A finite number >= 0."""
    if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


def discount(name: str, value: object) -> float:
    """A discount factor in (0, 1]."""
    if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and 0 < value <= 1):
        raise ValueError(f"{name} must be a discount factor in (0, 1], got {value!r}")
    return float(value)


def _positive_finite(name: str, value: object) -> float:
    if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def substeps(control_hz: object, physics_dt: object) -> int:
    """Physics steps per control step: the control period must be a whole number (>= 1) of ``physics_dt``."""
    hz, dt = _positive_finite("control_hz", control_hz), _positive_finite("physics_dt", physics_dt)
    ratio = 1.0 / (hz * dt)
    n = round(ratio)
    if n < 1 or not math.isclose(ratio, n, rel_tol=_SUBSTEP_RTOL):
        raise ValueError(f"physics_dt={physics_dt!r} must divide the control period 1/control_hz = {1.0 / hz:g} s "
                         f"into a whole number (>= 1) of substeps, got {ratio:g}; choose physics_dt = "
                         f"{1.0 / hz:g} / n for a whole n >= 1")
    return n
