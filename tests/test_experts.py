"""Every task's scripted expert solves it; the full 50-seed table is a slow test."""

from __future__ import annotations

import pytest

from conftest import FRANKA_TASKS
from dust_rl.envs import DustEnv
from dust_rl.expert_rollouts import expert_success_table, run_expert_episode


@pytest.mark.parametrize("task", FRANKA_TASKS)
def test_expert_solves_task(task):
    env = DustEnv(task=task, obs_mode="state")
    for seed in (0, 1):
        result = run_expert_episode(env, seed)
        assert result.success, f"{task} seed {seed}: {result}"
        assert result.length < env.max_episode_steps


@pytest.mark.parametrize("task", FRANKA_TASKS)
def test_dense_reward_rises_along_expert_episode(task):
    env = DustEnv(task=task, obs_mode="state", reward_type="dense")
    env.reset(seed=3)
    expert = env.make_expert()
    rewards = []
    for _ in range(env.max_episode_steps):
        _, reward, terminated, truncated, _ = env.step(expert.act(*env.end_effector_pose()))
        rewards.append(reward)
        if terminated or truncated:
            break
    assert all(0.0 <= r <= 1.0 for r in rewards)
    assert rewards[-1] == 1.0 and max(rewards[:-1]) < 1.0
    assert rewards[len(rewards) // 2] > rewards[0]


@pytest.mark.slow
def test_expert_success_table_50_seeds():
    rows = expert_success_table("DustFranka-v0", FRANKA_TASKS, seeds=50)
    for row in rows:
        assert row["success_rate"] >= 0.95, row
