"""Headless, fast offscreen rendering.

MuJoCo's default visual settings cost ~300 ms per frame on a CPU-only
machine (4096 shadow map, MSAA, 400k-vertex meshes). Fast mode turns off
shadows, reflections and multisampling and draws the robots' low-poly
collision geometry instead of their visual meshes, which keeps a 128x128
frame at about a millisecond while arms, grippers and objects stay
recognisable.
"""

from __future__ import annotations

import atexit
import ctypes.util
import os
import weakref

VISUAL_GROUP = 2
COLLISION_GROUP = 3
RENDER_QUALITIES = ("fast", "visual")


def configure_headless_gl() -> str:
    """Pick a headless OpenGL backend unless the user chose one.

    Must run before ``mujoco`` is imported: MuJoCo reads ``MUJOCO_GL`` once.
    EGL is preferred; OSMesa is the fallback when no libEGL is installed.
    """
    if "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "egl" if ctypes.util.find_library("EGL") else "osmesa"
    if os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    return os.environ["MUJOCO_GL"]


configure_headless_gl()

import mujoco  # noqa: E402  (must follow configure_headless_gl)
import numpy as np  # noqa: E402


class CameraRenderer:
    """Renders named cameras of one model to uint8 RGB arrays."""

    def __init__(self, model: mujoco.MjModel, height: int, width: int, quality: str = "fast") -> None:
        if quality not in RENDER_QUALITIES:
            raise ValueError(f"unknown render quality {quality!r}; expected one of {RENDER_QUALITIES}")
        if quality == "fast":
            model.vis.quality.shadowsize = 0
            model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        self._renderer = mujoco.Renderer(model, height, width)
        _track_for_exit(self)
        flags = self._renderer.scene.flags
        if quality == "fast":
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        self._option = mujoco.MjvOption()
        self._option.geomgroup[VISUAL_GROUP] = quality == "visual"
        self._option.geomgroup[COLLISION_GROUP] = quality == "fast"

    def render(self, data: mujoco.MjData, camera: str) -> np.ndarray:
        self._renderer.update_scene(data, camera, self._option)
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()
        _LIVE_RENDERERS.discard(self)


_LIVE_RENDERERS: weakref.WeakSet[CameraRenderer] = weakref.WeakSet()
_exit_hook_registered = False


def _track_for_exit(renderer: CameraRenderer) -> None:
    """Close still-open renderers at exit before MuJoCo's EGL module terminates the display.

    ``atexit`` runs hooks last-in first-out, so the hook must be registered after
    ``mujoco.egl`` (imported by the first ``mujoco.Renderer``) registered its own.
    """
    global _exit_hook_registered
    if not _exit_hook_registered:
        atexit.register(_close_live_renderers)
        _exit_hook_registered = True
    _LIVE_RENDERERS.add(renderer)


def _close_live_renderers() -> None:
    for renderer in list(_LIVE_RENDERERS):
        renderer.close()
