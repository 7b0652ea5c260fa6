"""Bad actions raise clear errors; IK failure and diverging physics truncate instead of crashing."""

from __future__ import annotations

import mink
import numpy as np
import pytest

from dust_rl.envs import DustEnv


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action_raises(state_env, bad):
    state_env.reset(seed=0)
    action = np.zeros(7, np.float32)
    action[2] = bad
    with pytest.raises(ValueError, match="NaN or infinite"):
        state_env.step(action)


@pytest.mark.parametrize("shape", [(6,), (8,), (1, 7), ()])
def test_wrong_shape_raises(state_env, shape):
    state_env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        state_env.step(np.zeros(shape, np.float32))


def test_out_of_range_action_is_clipped():
    envs = [DustEnv(task="pick_place", obs_mode="state") for _ in range(2)]
    for env in envs:
        env.reset(seed=5)
    big = np.array([3.0, -5.0, 2.0, 0.0, 9.0, -2.0, 4.0], np.float32)
    obs_big = envs[0].step(big)[0]
    obs_clipped = envs[1].step(np.clip(big, -1, 1))[0]
    np.testing.assert_array_equal(obs_big["agent_pos"], obs_clipped["agent_pos"])


def test_ik_failure_truncates_episode():
    env = DustEnv(task="pick_place", obs_mode="state")
    env.reset(seed=0)
    # A real, infeasible QP: joint limits that exclude the robot's current configuration.
    model = env.controller.model
    saved = model.jnt_range.copy()
    model.jnt_range[0] = (2.0, 2.5)
    env.controller.limits.append(mink.ConfigurationLimit(model))
    model.jnt_range[:] = saved
    _, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert truncated and not terminated and reward == 0.0
    assert info["truncation_reason"] == "ik_failure"


def test_diverging_physics_truncates_episode():
    env = DustEnv(task="pick_place", obs_mode="state")
    env.reset(seed=0)
    env.data.joint("target_cube_joint").qvel[:] = 1e30
    obs, _, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert truncated and not terminated
    assert info["truncation_reason"] == "physics_unstable"


def test_time_limit_truncates(state_env):
    env = DustEnv(task="pick_place", obs_mode="state", max_episode_steps=3)
    env.reset(seed=0)
    reasons = [env.step(np.zeros(7, np.float32))[4]["truncation_reason"] for _ in range(3)]
    assert reasons == ["", "", "time_limit"]
