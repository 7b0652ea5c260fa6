"""Pick into bin: drop the object named by colour and shape into an open bin, among two distractors."""

from __future__ import annotations

import mujoco
import numpy as np

from ..experts import Waypoint
from ..robot import RobotConfig
from ..scene import GEOM, add_free_box, add_free_cylinder
from .base import COLORS, Task, geoms_touch, sample_separated, set_free_body_pose, yaw_features
from .fixtures import add_walled_square, local_xyz, set_mocap_pose
from .grasping import grasp_yaw, gripper_geoms, pick_and_place

OBJECT_HALF = 0.02  # cube half size; cylinder radius and half height
BIN_INNER_HALF = 0.075  # wide enough for the open fingers to release inside the walls
BIN_OUTER_HALF = 0.085
BIN_WALL_HEIGHT = 0.04
BIN_FLOOR_HEIGHT = 0.004
# Shapes are fixed at build time; reset draws the target's shape first so both are targets equally often.
OBJECTS = (("cube_a", "cube"), ("cube_b", "cube"), ("cylinder", "cylinder"))
_TEMPLATES = (
    "put the {color} {shape} in the bin",
    "place the {color} {shape} into the bin",
    "pick up the {color} {shape} and drop it in the bin",
)
_AREA = (np.array([0.3, -0.28]), np.array([0.62, 0.28]))
_BIN_AREA = (np.array([0.4, -0.2]), np.array([0.52, 0.2]))
_OBJECT_SPACING = 0.11  # open fingers fit between objects
_BIN_CLEARANCE = 0.18  # open fingers around an object stay clear of the bin walls at any bin yaw


class PickIntoBin(Task):
    name = "pick_into_bin"
    category = "pick_and_place"
    max_episode_steps = 200
    # target xyz, two distractors xyz, bin xyz, then the yaws of those four (sin, cos of 4 x yaw; a cylinder's 0, 0)
    environment_state_dim = 20

    def build(self, spec: mujoco.MjSpec) -> None:
        for body, shape in OBJECTS:
            if shape == "cube":
                add_free_box(spec, body, (OBJECT_HALF,) * 3)
            else:
                add_free_cylinder(spec, body, OBJECT_HALF, OBJECT_HALF)
        bin_body = add_walled_square(spec, "bin", BIN_INNER_HALF, BIN_OUTER_HALF, BIN_WALL_HEIGHT)
        bin_body.add_geom(name="bin_floor", type=GEOM.mjGEOM_BOX,
                          size=(BIN_OUTER_HALF, BIN_OUTER_HALF, BIN_FLOOR_HEIGHT / 2),
                          pos=(0, 0, BIN_FLOOR_HEIGHT / 2), rgba=(0.4, 0.42, 0.45, 1))

    def bind(self, model: mujoco.MjModel, robot: RobotConfig) -> None:
        self._gripper_geoms = gripper_geoms(model, robot)
        self._pinch = robot.end_effectors[0].site
        self._objects = [body for body, _ in OBJECTS]  # target first once reset

    def reset(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> str:
        bin_xy, object_xys = self._layout(rng)
        shape = str(rng.choice(sorted({s for _, s in OBJECTS})))
        target = str(rng.choice([body for body, s in OBJECTS if s == shape]))
        self._objects = [target, *(body for body, _ in OBJECTS if body != target)]
        colors = list(rng.permutation(list(COLORS))[:3])
        # Half the time a distractor of the other shape shares the target's colour, so both words matter.
        other = next(body for body, s in OBJECTS if s != shape)
        if rng.random() < 0.5:
            colors[self._objects.index(other)] = colors[0]
        for body, color, xy in zip(self._objects, colors, object_xys):
            model.geom(body).rgba = COLORS[color]
            set_free_body_pose(data, body, np.r_[xy, OBJECT_HALF], rng.uniform(-np.pi / 4, np.pi / 4))
        set_mocap_pose(model, data, "bin", bin_xy, rng.uniform(-np.pi / 4, np.pi / 4))
        return str(rng.choice(_TEMPLATES)).format(color=colors[0], shape=shape)

    @staticmethod
    def _layout(rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray]]:
        """Bin and object positions, objects spaced for grasping and clear of the bin."""
        for _ in range(1000):
            bin_xy = rng.uniform(*_BIN_AREA)
            object_xys = sample_separated(rng, len(OBJECTS), *_AREA, min_distance=_OBJECT_SPACING)
            if all(np.linalg.norm(xy - bin_xy) >= _BIN_CLEARANCE for xy in object_xys):
                return bin_xy, object_xys
        raise RuntimeError("could not lay out the bin and objects")

    def _in_bin(self, data: mujoco.MjData) -> bool:
        local = local_xyz(data, "bin", self._objects[0])
        resting = local[2] < BIN_FLOOR_HEIGHT + OBJECT_HALF + 0.01
        return bool(np.all(np.abs(local[:2]) < BIN_INNER_HALF) and resting)

    def is_success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        target = np.array([model.geom(self._objects[0]).id])
        return self._in_bin(data) and not geoms_touch(data, self._gripper_geoms, target)

    def progress(self, model: mujoco.MjModel, data: mujoco.MjData, eef_pos: np.ndarray) -> float:
        target, bin_pos = data.body(self._objects[0]).xpos, data.body("bin").xpos
        reach = np.exp(-10 * np.linalg.norm(eef_pos - target))
        place = np.exp(-10 * np.linalg.norm(target[:2] - bin_pos[:2]))
        lifted = float(target[2] > OBJECT_HALF + 0.02)
        return float(0.25 * reach + 0.25 * lifted + 0.45 * place * (lifted or self._in_bin(data)))

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        bodies, shape = (*self._objects, "bin"), dict(OBJECTS)
        return np.concatenate([*(data.body(b).xpos for b in bodies),
                               *(np.zeros(2) if shape.get(b) == "cylinder" else yaw_features(data, b) for b in bodies)])

    def expert_plan(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Waypoint]:
        target = self._objects[0]
        goal = data.body("bin").xpos + [0, 0, BIN_FLOOR_HEIGHT + OBJECT_HALF + 0.01]
        yaw = grasp_yaw(data, target, square=dict(OBJECTS)[target] == "cube")
        return pick_and_place(data, target, self._pinch, goal, yaw)
