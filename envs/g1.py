"""Unitree G1 humanoid with Dex3 hands (Menagerie ``g1_with_hands``), fixed behind the table.

Tabletop work needs no balancing: the free joint and the leg joints are
removed, so the pelvis is welded in place and the legs are rigid scenery
below the table. The waist and both arms are driven through inverse
kinematics; each hand closes through a grasp synergy of its seven finger
joints.
"""

from __future__ import annotations

import functools
import pathlib

import mujoco
import numpy as np

from .assets import robot_xml
from .rendering import COLLISION_GROUP
from .robot import EndEffector, RobotConfig
from .scene import FLOOR_Z

_PREFIX = "g1/"
BASE_X = -0.2  # pelvis position: the torso stops 2 cm short of the table edge (x = -0.1)
SIDES = ("left", "right")  # end-effector (action) order
_WAIST_JOINTS = ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint")
_ARM_JOINTS = ("shoulder_pitch_joint", "shoulder_roll_joint", "shoulder_yaw_joint", "elbow_joint",
               "wrist_roll_joint", "wrist_pitch_joint", "wrist_yaw_joint")
_FINGER_JOINTS = ("thumb_0_joint", "thumb_1_joint", "thumb_2_joint", "index_0_joint", "index_1_joint",
                  "middle_0_joint", "middle_1_joint")
_LEG_PARTS = ("hip", "knee", "ankle")
# Left hand, in _FINGER_JOINTS order; the right hand's joints turn the other way except thumb_0.
_OPEN = np.zeros(7)
_CLOSED = np.array([0.0, 0.6, 1.2, -1.0, -1.2, -1.0, -1.2])
_FINGER_MIRROR = np.array([1.0, -1.0, -1.0, -1.0, -1.0, -1.0, -1.0])
# Left arm, in _ARM_JOINTS order; the right arm mirrors roll and yaw.
_HOME_ARM = np.array([0.58, 0.616, 0.181, -0.737, -0.666, 0.136, 0.141])  # palm at (0, 0.18, 0.22), side grasp
_ARM_MIRROR = np.array([1.0, -1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
# Palm facing the midline (left palm toward -y, right toward +y), fingers forward: the hands
# close around an object's side. This is the arms' zero pose, far from the joint limits.
_SIDE_GRASP = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
# Absolute-mode position box (table frame): in front of the robot, over the table's near part.
_WORKSPACE = ((-0.1, -0.4, 0.0), (0.35, 0.4, 0.4))
_FINGER_KP = 10.0
# The palm site is the grasp centre: where an object's axis sits when the open hand comes down
# beside it, PALM_DEPTH off the palm's surface and OPEN_THUMB_BEHIND ahead of the open thumb
# (1.5 cm of clearance on both for a 5.6 cm can), with the straight fingers reaching past it.
PALM_DEPTH = 0.044
OPEN_THUMB_BEHIND = 0.042
_PALM_SITE = (0.115, 0.016 + PALM_DEPTH)  # wrist frame: along the fingers, toward the palm side
_VMAX_ARM = 3.0
_VMAX_WAIST = 1.0
_WAIST_POSTURE_COST = 0.05  # the arms reach; the waist leans in only for the far side of the table
_HULL_DIRECTIONS = 96  # support directions of the low-poly collision hulls


def add_g1(spec: mujoco.MjSpec, base_x: float = BASE_X) -> RobotConfig:
    """Attach the G1 to ``spec``, standing on the floor behind the table, with palm sites and cameras."""
    base = spec.worldbody.add_site(name="robot_base", pos=(base_x, 0.0, FLOOR_Z))
    spec.attach(_tabletop_g1(spec.option.integrator), site=base, prefix=_PREFIX)
    torso = spec.body(f"{_PREFIX}torso_link")
    # Looks down at the near half of the table (x = 0.13 with the waist straight), like GR-1's head camera.
    torso.add_camera(name="head", pos=(0.09, 0.0, 0.44), xyaxes=(0, -1, 0, 0.91, 0, 0.42), fovy=62)
    torso_geoms = _name_collision_geoms(torso, "torso", recursive=False)
    hand_geoms = {}
    for side, sign in zip(SIDES, (1.0, -1.0)):
        wrist = spec.body(f"{_PREFIX}{side}_wrist_yaw_link")
        wrist.add_site(name=f"{side}_palm", pos=(_PALM_SITE[0], -sign * _PALM_SITE[1], 0.0), size=(0.005, 0, 0),
                       rgba=(1, 0, 0, 0), group=4)
        # Above the palm side of the wrist, looking along the fingers and down past them.
        wrist.add_camera(name=f"{side}_wrist", pos=(0.0, -sign * 0.06, 0.05), xyaxes=(0, -1, 0, 0.6, 0, 0.8), fovy=80)
        hand_geoms[side] = _name_collision_geoms(wrist, f"{side}_hand")
    arm_joints = tuple(_PREFIX + j for j in _WAIST_JOINTS) + tuple(
        f"{_PREFIX}{side}_{j}" for side in SIDES for j in _ARM_JOINTS)
    home = np.concatenate([np.zeros(len(_WAIST_JOINTS)), _HOME_ARM, _HOME_ARM * _ARM_MIRROR])
    both_hands = hand_geoms["left"] + hand_geoms["right"]
    return RobotConfig(
        name="humanoid",
        arm_joints=arm_joints,
        arm_actuators=arm_joints,  # Menagerie names each actuator after its joint
        end_effectors=tuple(_hand(side) for side in SIDES),
        home_qpos=dict(zip(arm_joints, home)),
        cameras=("head", "left_wrist", "right_wrist"),
        default_cameras=("head",),
        max_joint_velocity={j: _VMAX_WAIST if "waist" in j else _VMAX_ARM for j in arm_joints},
        workspace=_WORKSPACE,
        # Hands apart, and off the table and torso: measured +0.07 ms per IK solve (0.23 -> 0.30 ms).
        collision_pairs=((hand_geoms["left"], hand_geoms["right"]), (both_hands, ("table", *torso_geoms))),
        posture_costs=dict.fromkeys(arm_joints[:len(_WAIST_JOINTS)], _WAIST_POSTURE_COST),
    )


def _tabletop_g1(integrator: mujoco.mjtIntegrator) -> mujoco.MjSpec:
    """Menagerie's G1 with its pelvis welded, legs rigid and out of contact, and soft finger servos."""
    xml = robot_xml("unitree_g1", "g1_with_hands")
    g1 = mujoco.MjSpec.from_file(str(xml))
    g1.option.integrator = integrator
    g1.delete(g1.joint("floating_base_joint"))
    legs = tuple(f"{side}_{part}" for side in SIDES for part in _LEG_PARTS)
    for element in [*g1.lights, *g1.keys, *g1.sensors, *(a for a in g1.actuators if a.name.startswith(legs)),
                    *(j for j in g1.joints if j.name.startswith(legs))]:
        g1.delete(element)
    _use_low_poly_collision_meshes(g1, xml.parent / g1.meshdir)
    for body in g1.bodies:
        body.gravcomp = 1.0
    for actuator in g1.actuators:
        if "_hand_" in actuator.name:
            # Menagerie's finger servos (kp 500) saturate their 1.4 Nm limit on any closure step,
            # which removes their damping: the fingers overshoot by half a radian. A soft servo
            # (kp 10, still critically damped) closes in about 0.1 s and grips at the same limit.
            actuator.gainprm[0], actuator.biasprm[1] = _FINGER_KP, -_FINGER_KP
    for geom in _collision_geoms(g1.worldbody):
        # Touch the world (contype 1) but not the robot's own links; the legs touch nothing.
        geom.contype, geom.conaffinity = (0, 0) if geom.parent.name.startswith(("pelvis", *legs)) else (2, 1)
    return g1


def _hand(side: str) -> EndEffector:
    """A Dex3 hand driven by one closure through its finger synergy."""
    joints = tuple(f"{_PREFIX}{side}_hand_{j}" for j in _FINGER_JOINTS)
    mirror = 1.0 if side == "left" else _FINGER_MIRROR
    closed = _CLOSED * mirror
    curling = closed != 0
    return EndEffector(
        site=f"{side}_palm",
        actuators=joints,  # Menagerie names each actuator after its joint
        open_ctrl=tuple(_OPEN * mirror),
        closed_ctrl=tuple(closed),
        opening_joints=joints,
        grasp_rotation=_SIDE_GRASP,
        # Mean curl of the fingers toward the closed synergy, negated: 0 open, -1 closed.
        opening_weights=tuple(np.where(curling, -1.0 / (curling.sum() * np.where(curling, closed, 1.0)), 0.0)),
    )


def _collision_geoms(body: mujoco.MjsBody, recursive: bool = True) -> list[mujoco.MjsGeom]:
    """Menagerie's collision geoms (group 3; the visual meshes are group 2)."""
    geoms = body.find_all(mujoco.mjtObj.mjOBJ_GEOM) if recursive else body.geoms
    return [g for g in geoms if g.group == COLLISION_GROUP]


def _name_collision_geoms(body: mujoco.MjsBody, stem: str, recursive: bool = True) -> tuple[str, ...]:
    """Name the collision geoms of ``body`` (and its subtree) ``stem_0, stem_1, ...`` for the IK's collision pairs."""
    names = []
    for i, geom in enumerate(_collision_geoms(body, recursive)):
        geom.name = f"{stem}_{i}"
        names.append(geom.name)
    return tuple(names)


def _use_low_poly_collision_meshes(g1: mujoco.MjSpec, mesh_dir: pathlib.Path) -> None:
    """Give each collision geom a low-poly convex hull of its mesh.

    MuJoCo collides meshes through their convex hulls anyway, so physics barely
    changes, but the hulls of these 600k-triangle scans still have ~85k faces.
    A hull through ~100 support points keeps the links recognisable in the fast
    renderer (which draws collision geoms) at a fraction of the cost (2 ms
    instead of 55 ms per 128x128 head frame), and skips MuJoCo's hull
    computation at compile time.
    """
    hulls: dict[str, str] = {}
    for geom in _collision_geoms(g1.worldbody):
        if geom.type != mujoco.mjtGeom.mjGEOM_MESH:
            continue
        if geom.meshname not in hulls:
            hulls[geom.meshname] = f"{geom.meshname}_hull"
            points = _support_points(str(mesh_dir / g1.mesh(geom.meshname).file))
            g1.add_mesh(name=hulls[geom.meshname], uservert=points.ravel())
        geom.meshname = hulls[geom.meshname]


@functools.cache
def _support_points(stl_path: str) -> np.ndarray:
    """Extreme vertices of a binary STL mesh along evenly spread directions (a low-poly hull)."""
    triangles = np.fromfile(stl_path, dtype=np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)),
                                                      ("attribute", "<u2")]), offset=84)
    vertices = triangles["vertices"].reshape(-1, 3)
    extremes = np.argmax(_fibonacci_sphere(_HULL_DIRECTIONS).astype(np.float32) @ vertices.T, axis=1)
    return vertices[np.unique(extremes)].astype(np.float64)


def _fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the sphere."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    angle = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z**2)
    return np.column_stack([r * np.cos(angle), r * np.sin(angle), z])
