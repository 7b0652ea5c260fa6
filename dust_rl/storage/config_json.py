"""Provenance for the files a run writes (config.json, reports, dataset metadata): the command's dataclass config
as JSON values and the versions of the packages that shaped the result."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import platform

_VERSIONED_PACKAGES = ("dust-rl", "mujoco", "torch", "torchrl", "tensordict", "gymnasium")


def config_json(config: object) -> dict:
    """``config`` (a dataclass) as plain JSON values: paths become strings, tuples lists."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


def package_versions() -> dict[str, str | None]:
    """Python's version and those of the packages that shape datasets and runs (None: not installed).

    Recorded in dataset metadata and in each training run's ``config.json``.
    """
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in _VERSIONED_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions
