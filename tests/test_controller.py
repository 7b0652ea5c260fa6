"""The mink operational-space controller moves the end effector as commanded."""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import pytest

from dust_rl.envs.env import MAX_ROTATION, MAX_TRANSLATION


def _run(env, action, steps):
    for _ in range(steps):
        env.step(np.asarray(action, np.float32))
    return env.end_effector_pose()


def test_zero_action_holds_still(state_env):
    state_env.reset(seed=0)
    pos0, rot0 = state_env.end_effector_pose()
    pos, rot = _run(state_env, np.zeros(7), 40)
    assert np.linalg.norm(pos - pos0) < 2e-3
    assert np.abs(rot - rot0).max() < 1e-2


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_delta_translation_follows_axis(state_env, axis):
    state_env.reset(seed=0)
    pos0, _ = state_env.end_effector_pose()
    action = np.zeros(7)
    action[axis] = 0.5
    pos, _ = _run(state_env, action, 10)
    moved = pos - pos0
    expected = 10 * 0.5 * MAX_TRANSLATION
    assert 0.6 * expected < moved[axis] < 1.1 * expected
    assert np.abs(np.delete(moved, axis)).max() < 0.2 * expected


def test_delta_rotation_about_world_z(state_env):
    state_env.reset(seed=0)
    _, rot0 = state_env.end_effector_pose()
    _, rot = _run(state_env, [0, 0, 0, 0, 0, 0.5, 0], 8)
    relative = rot @ rot0.T
    angle = np.arctan2(relative[1, 0], relative[0, 0])
    assert 0.6 * 8 * 0.5 * MAX_ROTATION < angle < 1.1 * 8 * 0.5 * MAX_ROTATION


def test_gripper_closes_and_opens(state_env):
    state_env.reset(seed=0)
    opening = lambda: state_env._state()[-1]  # noqa: E731
    open_width = opening()
    _run(state_env, [0, 0, 0, 0, 0, 0, 1], 15)
    closed_width = opening()
    _run(state_env, [0, 0, 0, 0, 0, 0, -1], 15)
    assert closed_width < 0.01 < 0.07 < open_width
    assert opening() > 0.07


def test_placement_puts_the_end_effector_at_a_pose_and_the_fingers_toward_their_closure(state_env):
    sim = state_env.unwrapped
    sim.reset_unobserved(seed=0)
    pos0, rot0 = sim.end_effector_pose()
    opening0 = sim._state()[-1]
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, rot0.ravel())
    target = pos0 + np.array([0.05, -0.04, -0.03])
    sim.place_end_effectors([mink.SE3(np.r_[quat, target])], [1.0])
    pos, rot = sim.end_effector_pose()
    # Within a millimetre: the IK converges to ~1e-6 m; the settling physics holds the joints at their targets.
    assert np.linalg.norm(pos - target) < 1e-3
    assert np.abs(rot - rot0).max() < 1e-2
    assert sim._state()[-1] < 0.75 * opening0  # the fingers on their way to closed
    with pytest.raises(ValueError, match="one of each per end effector"):
        sim.place_end_effectors([mink.SE3(np.r_[quat, target])] * 2, [1.0, 1.0])


def test_a_placement_out_of_the_workspace_stops_at_its_edge(state_env):
    sim = state_env.unwrapped
    sim.reset_unobserved(seed=0)
    pos0, rot0 = sim.end_effector_pose()
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, rot0.ravel())
    sim.place_end_effectors([mink.SE3(np.r_[quat, pos0 + [0.0, 0.0, 5.0]])], [0.0])
    assert sim.end_effector_pose()[0][2] <= sim.robot.workspace[1][2] + 1e-3


def test_reset_unobserved_then_observe_is_reset(rgb_env):
    sim = rgb_env.unwrapped
    obs, _ = rgb_env.reset(seed=3)
    sim.reset_unobserved(seed=3)
    again = sim.observe()
    assert obs.keys() == again.keys()
    assert all(np.array_equal(obs[k], again[k]) for k in obs if k != "language_instruction")
    assert obs["language_instruction"] == again["language_instruction"]
