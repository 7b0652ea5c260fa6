"""Every task's scripted expert solves it, in both suites; the full 50-seed tables are slow tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import SUITE_TASKS

from dust_rl.data.expert_rollouts import expert_success_table, run_expert_episode
from dust_rl.envs import DustEnv, list_tasks
from dust_rl.envs.registration import ENV_IDS


@pytest.mark.parametrize(("robot", "task"), SUITE_TASKS)
def test_expert_solves_task(robot, task):
    env = DustEnv(task=task, robot=robot, obs_mode="state")
    for seed in (0, 1):
        result, _ = run_expert_episode(env, seed)
        assert result.success, f"{robot} {task} seed {seed}: {result}"
        assert result.length < env.max_episode_steps


@pytest.mark.parametrize(("robot", "task"), SUITE_TASKS)
def test_dense_reward_is_discounted_shaping_along_expert_episode(robot, task):
    env = DustEnv(task=task, robot=robot, obs_mode="state", reward_type="dense")
    gamma = env.shaping_discount
    env.reset(seed=3)
    start = env.progress()
    expert = env.make_expert()
    rewards = []
    for _ in range(env.max_episode_steps):
        _, reward, terminated, truncated, _ = env.step(expert.act())
        rewards.append(reward)
        if terminated or truncated:
            break
    assert terminated and 0.0 <= start < 1.0
    # Potential-based for discount gamma: the discounted rewards telescope to the discounted success minus the
    # start's progress; float64 sums of float64 products, so the tolerance is a few ulps per step.
    discounted = math.fsum(gamma ** t * r for t, r in enumerate(rewards))
    assert abs(discounted - (gamma ** (len(rewards) - 1) - start)) <= 8 * len(rewards) * np.finfo(np.float64).eps
    assert math.fsum(rewards[:len(rewards) // 2]) > 0.0  # halfway, the expert has made progress


def test_dense_reward_pays_nothing_for_standing_still():
    env = DustEnv(task="press_button", obs_mode="state", reward_type="dense", shaping_discount=1.0)
    env.reset(seed=0)
    env.step(np.zeros(env.action_space.shape, np.float32))  # let the arm settle at rest
    before = env.progress()
    rewards = [env.step(np.zeros(env.action_space.shape, np.float32))[1] for _ in range(5)]
    assert abs(math.fsum(rewards) - (env.progress() - before)) <= 8 * 5 * np.finfo(np.float64).eps
    assert abs(math.fsum(rewards)) < 1e-3  # no per-step income (the arm at rest moves by micrometres)


def test_dense_reward_needs_a_discount_factor():
    for gamma in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"shaping_discount must be a discount factor in \(0, 1\]"):
            DustEnv(task="press_button", obs_mode="state", reward_type="dense", shaping_discount=gamma)


@pytest.mark.slow
@pytest.mark.parametrize(("env_id", "min_success"), [("DustFranka-v0", 0.95), ("DustHumanoid-v0", 0.9)])
def test_expert_success_table_50_seeds(env_id, min_success):
    rows = expert_success_table(env_id, list_tasks(ENV_IDS[env_id]), seeds=50)
    for row in rows:
        assert row["success_rate"] >= min_success, row
