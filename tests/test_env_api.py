"""The env satisfies gymnasium, torchrl and SB3 checkers and registers properly."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

from dust_rl.envs import DustEnv, list_tasks
from dust_rl.envs.torchrl_env import make_torchrl_env


def test_gymnasium_check_env_rgb(rgb_env):
    gym_check_env(rgb_env, skip_render_check=False)


def test_gymnasium_check_env_state(state_env):
    gym_check_env(state_env, skip_render_check=True)


def test_sb3_check_env_state_mode(state_env):
    sb3_check_env(state_env, warn=True, skip_render_check=True)


def test_torchrl_check_env_specs_gymenv():
    env = GymEnv("DustFranka-v0", task="pick_place", image_size=32)
    check_env_specs(env, seed=0)
    env.close()


def test_torchrl_canonical_keys():
    env = make_torchrl_env(task="pick_place", image_size=32)
    check_env_specs(env, seed=0)
    td = env.rollout(3)
    assert td["observation", "image", "front"].shape == (3, 3, 32, 32)
    assert td["observation", "state"].shape == (3, 17)
    assert "plate" in td["language_instruction"][0]
    env.close()


def test_spaces_and_observation_layout(rgb_env):
    obs, info = rgb_env.reset(seed=3)
    assert rgb_env.action_space.shape == (7,)
    assert obs["observation.image.front"].shape == (64, 64, 3)
    assert obs["observation.image.front"].dtype == np.uint8
    assert obs["observation.state"].dtype == np.float32
    assert set(info) == {"is_success", "task", "truncation_reason", "language_instruction"}
    assert obs["language_instruction"] == info["language_instruction"]
    assert info["task"] == "pick_place" and info["is_success"] is False
    assert rgb_env.render().shape == (64, 64, 3)


def test_state_mode_renders_nothing(state_env):
    obs, _ = state_env.reset(seed=0)
    assert set(obs) == {"observation.state", "observation.environment_state"}
    assert state_env._renderer is None


def test_list_tasks_and_unknown_task():
    tasks = list_tasks("franka")
    assert "pick_place" in tasks
    with pytest.raises(ValueError, match="pick_place"):
        DustEnv(task="no_such_task")
    with pytest.raises(ValueError, match="robot"):
        list_tasks("no_such_robot")


@pytest.mark.parametrize("kwarg, named", [({"obs_mode": "depth"}, "depth"), ({"control_mode": "joint"}, "joint"),
                                          ({"reward_type": "shaped"}, "shaped"), ({"cameras": ["nope"]}, "nope")])
def test_bad_constructor_arguments(kwarg, named):
    with pytest.raises(ValueError, match=named):
        DustEnv(task="pick_place", **kwarg)


def test_make_without_import_uses_module_prefix():
    code = ("import gymnasium as gym; env = gym.make('dust_rl:DustFranka-v0', task='pick_place', obs_mode='state');"
            "_, info = env.reset(seed=0); print(info['language_instruction'])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "plate" in out.stdout


def test_make_vec_async():
    envs = gym.make_vec("DustFranka-v0", num_envs=2, vectorization_mode="async",
                        task="pick_place", obs_mode="state")
    obs, _ = envs.reset(seed=[0, 1])
    obs, reward, terminated, truncated, info = envs.step(np.zeros((2, 7), np.float32))
    assert obs["observation.state"].shape == (2, 17)
    assert reward.shape == (2,) and info["task"].tolist() == ["pick_place", "pick_place"]
    envs.close()


def test_absolute_control_reaches_commanded_pose():
    env = DustEnv(task="pick_place", obs_mode="state", control_mode="absolute")
    env.reset(seed=0)
    target = np.array([0.5, 0.1, 0.25])
    low, high = (np.asarray(corner) for corner in env.robot.workspace)
    action = np.zeros(7, np.float32)
    action[:3] = 2 * (target - low) / (high - low) - 1
    action[3] = 1.0  # axis-angle (pi, 0, 0): gripper pointing down
    for _ in range(60):
        env.step(action)
    assert np.linalg.norm(env.end_effector_pose()[0] - target) < 0.01
