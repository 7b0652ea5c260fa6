"""Gymnasium registration: ``DustFranka-v0`` and ``DustHumanoid-v0`` (task chosen by the ``task`` kwarg)."""

from __future__ import annotations

import gymnasium as gym

ENV_IDS = {"DustFranka-v0": "franka", "DustHumanoid-v0": "humanoid"}


def register_envs() -> None:
    """Register the suites once; safe to call repeatedly."""
    for env_id, robot in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="dust_rl.envs.env:DustEnv", kwargs={"robot": robot},
                         disable_env_checker=False)
