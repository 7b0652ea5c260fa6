"""Static props on mocap bodies: walled squares (bins, peg holes), posed by reset."""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from ..scene import GEOM


def add_walled_square(spec: mujoco.MjSpec, name: str, inner_half: float, outer_half: float, height: float,
                      rgba: Sequence[float] = (0.55, 0.57, 0.6, 1)) -> mujoco.MjsBody:
    """A mocap body with four box walls around a square opening, standing on the table.

    The walls' geoms are named ``{name}_wall_{i}``. Mocap keeps the prop static under
    contact while reset can still move it.
    """
    body = spec.worldbody.add_body(name=name, mocap=True)
    half_thickness = (outer_half - inner_half) / 2
    offset = inner_half + half_thickness
    walls = (((0, offset), (outer_half, half_thickness)), ((0, -offset), (outer_half, half_thickness)),
             ((offset, 0), (half_thickness, inner_half)), ((-offset, 0), (half_thickness, inner_half)))
    for i, (xy, half_xy) in enumerate(walls):
        body.add_geom(name=f"{name}_wall_{i}", type=GEOM.mjGEOM_BOX, size=(*half_xy, height / 2),
                      pos=(*xy, height / 2), rgba=rgba)
    return body


def set_mocap_pose(model: mujoco.MjModel, data: mujoco.MjData, body: str, xy: np.ndarray, yaw: float) -> None:
    """Put a mocap body on the table at ``xy``, rotated by ``yaw`` about z."""
    mocap = model.body(body).mocapid[0]
    data.mocap_pos[mocap] = np.r_[xy, 0.0]
    data.mocap_quat[mocap] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))


def local_xyz(data: mujoco.MjData, frame: str, body: str) -> np.ndarray:
    """Position of ``body`` in the frame of the body ``frame`` (e.g. an object inside a rotated bin)."""
    reference = data.body(frame)
    return reference.xmat.reshape(3, 3).T @ (data.body(body).xpos - reference.xpos)
