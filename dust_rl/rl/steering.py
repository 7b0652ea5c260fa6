"""Noise-space steering (DSRL-style): an RL actor picks the initial action noise of a frozen DUST policy.

DUST's sampler is deterministic given its initial noise, so the noise is an
action space in which every point maps to a chunk the imitation policy
considers likely. An RL agent that chooses it improves a frozen policy
without touching its weights (Wagenmaker et al. 2025, "Steering Your
Diffusion Policy with Latent Space Reinforcement Learning"), and the base
policy stays recoverable: the noise the policy would have drawn itself gives
exactly its own chunk.

:class:`NoiseSteeringEnv`'s action is that noise, scaled from [-1, 1] to
``[-noise_bound, noise_bound]`` (a standard normal draw lies within +-2 for
95% of its entries), row-major [H * Da]; one step samples a chunk from it and
executes the chunk's first ``execute_steps`` actions, summing their rewards
discounted to the chunk's start by ``step_discount`` per env step: with the
env's dense reward shaped for that discount (``shaping_discount``), a chunk's
reward is then potential-based shaping for an agent whose discount per chunk
is ``step_discount ** execute_steps`` (the shaping telescopes within the chunk).
Observations: :mod:`dust_rl.rl.frozen_policy_env`. Any SB3 algorithm with
``MultiInputPolicy`` runs on it unchanged.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from dust_rl.agents import DustPolicy
from dust_rl.envs import arguments
from dust_rl.rl.frozen_policy_env import FrozenPolicyEnv


class NoiseSteeringEnv(FrozenPolicyEnv):
    """A dust-rl env whose action is a frozen DUST policy's initial action noise; one step runs one chunk.

    Args:
        env: a dust-rl gymnasium env in image mode.
        policy: the frozen policy.
        noise_bound: the largest noise magnitude an action of +-1 maps to.
        execute_steps: env steps per chunk; default: the policy's own.
        step_discount: per env step, the discount of the rewards within a chunk (module doc); 1: their sum.
        finite_horizon: see :class:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv`.
    """

    def __init__(self, env: gym.Env, policy: DustPolicy, noise_bound: float = 2.0,
                 execute_steps: int | None = None, step_discount: float = 1.0, finite_horizon: bool = False) -> None:
        if not (np.isfinite(noise_bound) and noise_bound > 0):
            raise ValueError(f"noise_bound must be a positive number, got {noise_bound}")
        super().__init__(env, policy, execute_steps, finite_horizon)
        self.noise_bound, self.step_discount = float(noise_bound), arguments.discount("step_discount", step_discount)
        self.chunk_shape = (policy.config.horizon, policy.config.action_dim)
        self.action_space = spaces.Box(-1.0, 1.0, (int(np.prod(self.chunk_shape)),), np.float32)

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Sample a chunk from the noise ``action`` and execute its first ``execute_steps`` actions.

        Raises:
            ValueError, RuntimeError: see :meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.check_action`.
        """
        noise = torch.from_numpy(self.check_action(action) * self.noise_bound).view(1, *self.chunk_shape)
        return self._execute(self.plan(noise))

    def step_base(self) -> tuple[dict, float, bool, bool, dict]:
        """One step of the base policy: the chunk from the noise it draws itself (which may exceed the bound)."""
        if self.features is None:
            raise RuntimeError("call reset() before step_base()")
        return self._execute(self.plan())

    def _execute(self, chunk: torch.Tensor) -> tuple[dict, float, bool, bool, dict]:
        total, terminated, truncated, info = 0.0, False, False, {}
        for i, env_action in enumerate(chunk[:self.execute_steps].numpy()):
            obs, reward, terminated, truncated, info = self.env_step(env_action)
            total += self.step_discount ** i * float(reward)
            if terminated or truncated:
                break
        return self.observe(obs), total, terminated, truncated, info
