"""Programmatic tabletop scenes (MjSpec): floor, table, lights, cameras, props.

The table top is the plane z = 0 and the robot base sits at the origin, so
task code reads positions directly in table coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

TABLE_HALF_SIZE = (0.55, 0.6, 0.02)
TABLE_CENTER_X = 0.45
FLOOR_Z = -0.75

GEOM = mujoco.mjtGeom


def new_tabletop_spec(timestep: float = 0.002) -> mujoco.MjSpec:
    """An empty scene: floor, table, lights and the ``front`` camera."""
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.visual.headlight.ambient = (0.3, 0.3, 0.3)
    spec.visual.headlight.diffuse = (0.4, 0.4, 0.4)
    world = spec.worldbody
    world.add_geom(name="floor", type=GEOM.mjGEOM_PLANE, size=(3, 3, 0.1), pos=(0, 0, FLOOR_Z),
                   rgba=(0.35, 0.37, 0.4, 1))
    world.add_geom(name="table", type=GEOM.mjGEOM_BOX, size=TABLE_HALF_SIZE,
                   pos=(TABLE_CENTER_X, 0, -TABLE_HALF_SIZE[2]), rgba=(0.62, 0.5, 0.38, 1))
    world.add_light(name="key", pos=(0.6, 0.0, 2.0), dir=(0, 0, -1),
                    type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, diffuse=(0.6, 0.6, 0.6), castshadow=False)
    add_look_at_camera(spec, "front", eye=(1.15, 0.0, 0.6), target=(0.42, 0.0, 0.02), fovy=52)
    return spec


def add_look_at_camera(spec: mujoco.MjSpec, name: str, eye: Sequence[float], target: Sequence[float],
                       fovy: float = 45.0, body: mujoco.MjsBody | None = None) -> mujoco.MjsCamera:
    """A fixed camera at ``eye`` looking at ``target`` with world z up."""
    eye_v, target_v = np.asarray(eye, float), np.asarray(target, float)
    back = eye_v - target_v
    back /= np.linalg.norm(back)
    right = np.cross((0.0, 0.0, 1.0), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    parent = body if body is not None else spec.worldbody
    return parent.add_camera(name=name, pos=eye_v, xyaxes=np.concatenate([right, up]), fovy=fovy)


def add_free_box(spec: mujoco.MjSpec, name: str, half_size: Sequence[float], mass: float = 0.08,
                 rgba: Sequence[float] = (0.8, 0.2, 0.2, 1)) -> mujoco.MjsBody:
    """A free-floating box; its geom is named ``name`` so tasks can recolour it."""
    body = spec.worldbody.add_body(name=name)
    body.add_freejoint(name=f"{name}_joint")
    body.add_geom(name=name, type=GEOM.mjGEOM_BOX, size=half_size, mass=mass, rgba=rgba,
                  friction=(1.2, 0.01, 0.001), condim=4)
    return body


def add_free_cylinder(spec: mujoco.MjSpec, name: str, radius: float, half_height: float, mass: float = 0.08,
                      rgba: Sequence[float] = (0.2, 0.2, 0.8, 1)) -> mujoco.MjsBody:
    """A free-floating upright cylinder."""
    body = spec.worldbody.add_body(name=name)
    body.add_freejoint(name=f"{name}_joint")
    body.add_geom(name=name, type=GEOM.mjGEOM_CYLINDER, size=(radius, half_height, 0), mass=mass, rgba=rgba,
                  friction=(1.2, 0.01, 0.001), condim=4)
    return body


def add_marker(spec: mujoco.MjSpec, name: str, half_size: Sequence[float],
               rgba: Sequence[float]) -> mujoco.MjsBody:
    """A flat, non-colliding patch on the table (goal regions)."""
    body = spec.worldbody.add_body(name=name, mocap=True)
    body.add_geom(name=name, type=GEOM.mjGEOM_BOX, size=(half_size[0], half_size[1], 0.0005),
                  pos=(0, 0, 0.0005), rgba=rgba, contype=0, conaffinity=0)
    return body


def add_open_box(spec: mujoco.MjSpec, name: str, inner_half: float, wall_thickness: float, wall_height: float,
                 floor_thickness: float, rgba: Sequence[float] = (0.5, 0.5, 0.5, 1)) -> mujoco.MjsBody:
    """A static open-topped square box (bin, basket, pot) that reset can move: a mocap body.

    Its geoms are ``{name}_floor`` and ``{name}_wall_0..3``; the body frame is at the floor's centre.
    """
    body = spec.worldbody.add_body(name=name, mocap=True)
    outer = inner_half + wall_thickness
    body.add_geom(name=f"{name}_floor", type=GEOM.mjGEOM_BOX, size=(outer, outer, floor_thickness / 2),
                  pos=(0, 0, floor_thickness / 2), rgba=rgba)
    offset = inner_half + wall_thickness / 2
    across, along = (outer, wall_thickness / 2), (wall_thickness / 2, inner_half)
    for i, (xy, half) in enumerate((((0, offset), across), ((0, -offset), across), ((offset, 0), along),
                                    ((-offset, 0), along))):
        body.add_geom(name=f"{name}_wall_{i}", type=GEOM.mjGEOM_BOX, size=(*half, wall_height / 2),
                      pos=(*xy, wall_height / 2), rgba=rgba)
    return body
