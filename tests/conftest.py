"""Shared fixtures: real environments, built once per test module where possible."""

from __future__ import annotations

import pytest

import dust_rl  # noqa: F401  (registers the envs)
from dust_rl.envs import DustEnv, list_tasks

FRANKA_TASKS = list_tasks("franka")


@pytest.fixture(scope="module")
def state_env():
    env = DustEnv(task="pick_place", obs_mode="state")
    yield env
    env.close()


@pytest.fixture(scope="module")
def rgb_env():
    env = DustEnv(task="pick_place", image_size=64, render_mode="rgb_array")
    yield env
    env.close()
