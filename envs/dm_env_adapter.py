"""The tasks as ``dm_env.Environment``s, for agents and tools written against DeepMind's RL interface (Acme,
dm_env-based evaluators) rather than gymnasium's.

The adapter keeps the gymnasium env's meaning: the specs mirror its spaces (a bounded ``Box`` is a ``BoundedArray``,
an unbounded one an ``Array``, the instruction's ``Text`` a scalar ``StringArray``), success ends the episode with
discount 0 (``dm_env.termination``), and the time limit or a failed step (infeasible IK, diverging physics) ends it
with discount 1 (``dm_env.truncation``): the episode was cut short, not finished, so a learner should bootstrap. The
gymnasium info of the newest step (success flag, truncation reason) is kept in :attr:`DmEnvAdapter.info`, since a
``TimeStep`` has no field for it.

torchrl's ``DMControlWrapper`` cannot wrap it: it accepts only dm_control's ``control.Environment`` (it checks the
type and seeds through the env's ``task``). For torchrl, wrap the gymnasium env instead
(:func:`dust_rl.envs.torchrl_env.make_torchrl_env`).
"""

from __future__ import annotations

from typing import Any

import dm_env
import gymnasium as gym
import numpy as np
from dm_env import specs


def space_to_spec(space: gym.spaces.Space, name: str) -> specs.Array:
    """The dm_env spec of one gymnasium space of a DustEnv (``Box`` or ``Text``)."""
    if isinstance(space, gym.spaces.Box):
        if space.is_bounded("both"):
            return specs.BoundedArray(space.shape, space.dtype, space.low, space.high, name=name)
        return specs.Array(space.shape, space.dtype, name=name)
    if isinstance(space, gym.spaces.Text):
        return specs.StringArray((), str, name=name)
    raise TypeError(f"{name}: no dm_env spec for a {type(space).__name__} space; the adapter converts Box and Text "
                    f"spaces (a DustEnv's)")


class DmEnvAdapter(dm_env.Environment):
    """A gymnasium DustEnv (``gymnasium.make("DustFranka-v0", ...)`` or ``DustEnv(...)``) as a ``dm_env.Environment``.

    Args:
        env: the env to adapt; its observation space must be a ``Dict`` of ``Box`` and ``Text`` spaces and its
            action space a ``Box``. The adapter owns it: :meth:`close` closes it.
        seed: the seed of the first reset; later resets continue from the env's random state, so one seed
            reproduces a whole sequence of episodes (dm_env's ``reset`` takes no seed).
    """

    def __init__(self, env: gym.Env, seed: int | None = None) -> None:
        if not isinstance(env.observation_space, gym.spaces.Dict):
            raise TypeError(f"expected a Dict observation space (a DustEnv's), got {env.observation_space}")
        if not isinstance(env.action_space, gym.spaces.Box):
            raise TypeError(f"expected a Box action space (a DustEnv's), got {env.action_space}")
        self.env = env
        self._seed = seed
        self._observation_spec = {key: space_to_spec(space, key) for key, space in env.observation_space.items()}
        self._action_spec = space_to_spec(env.action_space, "action")
        self._needs_reset = True
        self.info: dict[str, Any] = {}

    def reset(self) -> dm_env.TimeStep:
        observation, self.info = self.env.reset(seed=self._seed)
        self._seed = None
        self._needs_reset = False
        return dm_env.restart(observation)

    def step(self, action: np.ndarray) -> dm_env.TimeStep:
        """One control step; after a ``LAST`` step (or before the first reset) it starts a new episode instead, as
        dm_env specifies, and ignores ``action``."""
        if self._needs_reset:
            return self.reset()
        observation, reward, terminated, truncated, self.info = self.env.step(
            np.asarray(action, dtype=self._action_spec.dtype))
        self._needs_reset = terminated or truncated
        if terminated:
            return dm_env.termination(reward, observation)
        if truncated:
            return dm_env.truncation(reward, observation)
        return dm_env.transition(reward, observation)

    def observation_spec(self) -> dict[str, specs.Array]:
        return self._observation_spec

    def action_spec(self) -> specs.Array:
        return self._action_spec

    def close(self) -> None:
        self.env.close()


def make_dm_env(env_id: str = "DustFranka-v0", seed: int | None = None, **kwargs: Any) -> DmEnvAdapter:
    """``gymnasium.make(env_id, **kwargs)`` as a ``dm_env.Environment``, e.g.
    ``make_dm_env(task="push", image_size=64, seed=0)``."""
    return DmEnvAdapter(gym.make(env_id, **kwargs), seed=seed)
