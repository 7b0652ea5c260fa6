"""Expose the scripted expert's action as an observation.

Demonstration collectors run many env processes; putting the expert inside
the env (rather than in the policy) lets the expert read the simulator
state in its own process, so any torchrl policy only has to read the
``"expert_action"`` key. The expert is rebuilt at every reset and queried
once per step, exactly as a direct expert rollout would query it, so with
the expert's action executed the trajectory is the expert's own. A terminal
observation (terminated or truncated) carries a zero label instead: no action
follows it, and an expert that plans (a search) would plan for nothing.

Another expert can stand in for the scripted one (``make_expert``): anything with ``act()``, built at each
reset from the env and the reset seed, e.g. an expert that searches with ``DustEnv.snapshot``/``restore``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import gymnasium as gym
import numpy as np

from dust_rl.keys import EXPERT_ACTION_KEY


class Expert(Protocol):
    def act(self) -> np.ndarray:
        """The action for the env's current state."""


def scripted_expert(env: gym.Env, seed: int | None) -> Expert:
    """The task's scripted waypoint expert (``DustEnv.make_expert``); it draws nothing, so ignores the seed."""
    return env.make_expert()


class ExpertActionWrapper(gym.Wrapper):
    """Adds ``"expert_action"`` (the expert's action for the current state) to every observation.

    Works on any env whose ``unwrapped`` has ``make_expert()``
    (``DustEnv``), e.g. ``ExpertActionWrapper(gym.make("DustFranka-v0", task="press_button"))``
    or, for torchrl, ``GymEnv(ExpertActionWrapper(...))`` / ``GymWrapper``.

    Args:
        env: the env.
        make_expert: builds the expert at every reset from ``env.unwrapped`` and the reset seed.
    """

    def __init__(self, env: gym.Env, make_expert: Callable[[gym.Env, int | None], Expert] = scripted_expert) -> None:
        super().__init__(env)
        if not isinstance(env.observation_space, gym.spaces.Dict):
            raise TypeError(f"ExpertActionWrapper needs a Dict observation space, got {env.observation_space}")
        if not hasattr(env.unwrapped, "make_expert"):
            raise TypeError(f"{type(env.unwrapped).__name__} has no scripted expert (make_expert)")
        action_space = env.action_space
        self.observation_space = gym.spaces.Dict({
            **env.observation_space.spaces,
            EXPERT_ACTION_KEY: gym.spaces.Box(-1.0, 1.0, action_space.shape, np.float32),
        })
        self._make_expert = make_expert
        self._expert: Expert | None = None

    def reset(self, **kwargs) -> tuple[dict, dict]:
        obs, info = self.env.reset(**kwargs)
        self._expert = self._make_expert(self.env.unwrapped, kwargs.get("seed"))
        return self._with_expert_action(obs), info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._with_expert_action(obs, final=terminated or truncated), reward, terminated, truncated, info

    def _with_expert_action(self, obs: dict, final: bool = False) -> dict:
        action = np.zeros(self.action_space.shape) if final else self._expert.act()
        return {**obs, EXPERT_ACTION_KEY: np.clip(action, -1.0, 1.0).astype(np.float32)}
