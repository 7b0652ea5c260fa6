"""stable-baselines3 trains on the env's state mode out of the box (a few hundred real steps per robot)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import SubprocVecEnv

import dust_rl  # noqa: F401  (registers the ids in this process)

pytestmark = pytest.mark.usefixtures("one_thread")

ENV_IDS = ["DustFranka-v0", "DustHumanoid-v0"]
TASKS = {"DustFranka-v0": "pick_place", "DustHumanoid-v0": "push"}
NET_ARCH = [16, 16]  # small: the point is that SB3 runs, not what it learns


def parameters(model) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone() for name, p in model.policy.named_parameters()}


def assert_trained(model, before: dict[str, torch.Tensor], steps: int) -> None:
    """All steps ran, learning moved every weight, and ``predict`` answers with an action in the space."""
    assert model.num_timesteps == steps
    unchanged = [name for name, p in parameters(model).items() if torch.equal(p, before[name])]
    assert not unchanged
    obs = model.get_env().observation_space.sample()
    action, _ = model.predict(obs, deterministic=True)
    assert model.action_space.contains(action.astype(np.float32))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sac_multi_input_policy_trains_on_a_plain_env(env_id):
    env = gym.make(env_id, task=TASKS[env_id], obs_mode="state")
    check_env(env, warn=True, skip_render_check=True)
    model = SAC("MultiInputPolicy", env, learning_starts=100, batch_size=32, buffer_size=1000,
                policy_kwargs={"net_arch": NET_ARCH}, seed=0)
    before = parameters(model)
    model.learn(total_timesteps=200)
    assert_trained(model, before, 200)
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_ppo_multi_input_policy_trains_on_subproc_vec_env(env_id):
    # The "dust_rl:" prefix lets each worker process import the package (and so register the ids) itself.
    envs = make_vec_env(f"dust_rl:{env_id}", n_envs=2, vec_env_cls=SubprocVecEnv,
                        env_kwargs={"task": TASKS[env_id], "obs_mode": "state"})
    try:
        model = PPO("MultiInputPolicy", envs, n_steps=64, batch_size=64, n_epochs=2,
                    policy_kwargs={"net_arch": NET_ARCH}, seed=0)
        before = parameters(model)
        model.learn(total_timesteps=256)
        assert_trained(model, before, 256)
    finally:
        envs.close()
