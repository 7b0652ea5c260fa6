"""Every task's scripted expert solves it, in both suites; the full 50-seed tables are slow tests."""

from __future__ import annotations

import pytest
from conftest import SUITE_TASKS

from dust_rl.envs import DustEnv, list_tasks
from dust_rl.envs.registration import ENV_IDS
from dust_rl.expert_rollouts import expert_success_table, run_expert_episode


@pytest.mark.parametrize(("robot", "task"), SUITE_TASKS)
def test_expert_solves_task(robot, task):
    env = DustEnv(task=task, robot=robot, obs_mode="state")
    for seed in (0, 1):
        result = run_expert_episode(env, seed)
        assert result.success, f"{robot} {task} seed {seed}: {result}"
        assert result.length < env.max_episode_steps


@pytest.mark.parametrize(("robot", "task"), SUITE_TASKS)
def test_dense_reward_rises_along_expert_episode(robot, task):
    env = DustEnv(task=task, robot=robot, obs_mode="state", reward_type="dense")
    env.reset(seed=3)
    expert = env.make_expert()
    rewards = []
    for _ in range(env.max_episode_steps):
        _, reward, terminated, truncated, _ = env.step(expert.act())
        rewards.append(reward)
        if terminated or truncated:
            break
    assert all(0.0 <= r <= 1.0 for r in rewards)
    assert rewards[-1] == 1.0 and max(rewards[:-1]) < 1.0
    assert rewards[len(rewards) // 2] > rewards[0]


@pytest.mark.slow
@pytest.mark.parametrize(("env_id", "min_success"), [("DustFranka-v0", 0.95), ("DustHumanoid-v0", 0.9)])
def test_expert_success_table_50_seeds(env_id, min_success):
    rows = expert_success_table(env_id, list_tasks(ENV_IDS[env_id]), seeds=50)
    for row in rows:
        assert row["success_rate"] >= min_success, row
