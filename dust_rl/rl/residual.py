"""Residual RL: a bounded correction added to each action a frozen DUST policy executes.

The other way to fine-tune without touching the imitation policy (ResiP,
Ankile et al. 2024; Policy Decorator, Yuan et al. 2024): the policy plans
chunks as it does in evaluation (receding horizon, its own sampling noise
restarted from the reset seed), and an RL agent adds ``residual_scale`` times
its action in [-1, 1]^Da to the action about to be executed, clipped to the
env's action box. A zero residual executes exactly the base policy's episode
(a trained policy's chunks already lie in the box: training sets its bounds).
The agent sees the base action it corrects beside the observation of
:mod:`dust_rl.rl.frozen_policy_env`; with ``world_model`` it (actor and critic
alike) also sees ``predicted_future``, the embedding of the frame at t+H that
DUST sampled jointly with the chunk being executed (normalised, [N_o * Dv]):
the world model's own guess at where that chunk leads, free, since the plan
computes it anyway.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from dust_rl.agents import DustPolicy
from dust_rl.agents.execution import replans
from dust_rl.rl.frozen_policy_env import FrozenPolicyEnv


class ResidualEnv(FrozenPolicyEnv):
    """A dust-rl env whose action is added, scaled, to a frozen DUST policy's next action.

    Args:
        env: a dust-rl gymnasium env in image mode.
        policy: the frozen policy.
        residual_scale: per action dimension, what an RL action of +-1 adds (a number or [Da]); default 10% of
            the action box's half-width.
        execute_steps: actions executed per chunk before the policy re-plans; default: the policy's own.
        world_model: also observe the predicted future of the chunk being executed (module doc).
        finite_horizon: see :class:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv`.

    Raises:
        ValueError: ``world_model`` with a policy that predicts no future (the action-only variant or sampler).
    """

    def __init__(self, env: gym.Env, policy: DustPolicy, residual_scale: float | np.ndarray | None = None,
                 execute_steps: int | None = None, world_model: bool = False, finite_horizon: bool = False) -> None:
        super().__init__(env, policy, execute_steps, finite_horizon)
        if world_model and policy.config.sampler_name == "action_only":
            raise ValueError(f"world_model needs a policy that predicts the future; this one (variant "
                             f"{policy.config.variant!r}, sampler {policy.config.sampler_name!r}) does not")
        low, high = env.action_space.low, env.action_space.high
        scale = 0.1 * (high - low) / 2 if residual_scale is None else residual_scale
        self.residual_scale = np.broadcast_to(np.asarray(scale, dtype=np.float32), low.shape).copy()
        if not (np.isfinite(self.residual_scale).all() and (self.residual_scale >= 0).all()):
            raise ValueError(f"residual_scale must be finite and >= 0, got {residual_scale}")
        self.action_space = spaces.Box(-1.0, 1.0, low.shape, np.float32)
        entries = {**self.observation_space.spaces, "base_action": env.action_space}
        if world_model:
            size = policy.config.n_vision_tokens * policy.config.vision_dim
            entries["predicted_future"] = spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.observation_space = spaces.Dict(entries)
        self.chunk, self.index = None, 0

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Execute the base action plus ``residual_scale * action``, clipped to the action box.

        Raises:
            ValueError, RuntimeError: see :meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.check_action`.
        """
        residual = self.check_action(action) * self.residual_scale
        executed = np.clip(self.base_action + residual, self.env.action_space.low, self.env.action_space.high)
        obs, reward, terminated, truncated, info = self.env_step(executed)
        self.index += 1
        return self.observe(obs), float(reward), terminated, truncated, info

    def step_base(self) -> tuple[dict, float, bool, bool, dict]:
        """One step of the base policy (a zero residual)."""
        return self.step(np.zeros(self.action_space.shape, np.float32))

    def observe(self, obs: dict) -> dict:
        """Also re-plan at the reset and when the chunk's executed part is used up (the evaluation's rule), and show
        the next base action."""
        view = super().observe(obs)
        if replans(len(self.executed), self.execute_steps):
            self.chunk, self.index = self.plan().numpy(), 0
        view["base_action"] = self.base_action
        if "predicted_future" in self.observation_space.spaces:
            view["predicted_future"] = self.predicted_future.astype(np.float32)
        return view

    @property
    def base_action(self) -> np.ndarray:
        """The action the base policy executes next."""
        return self.chunk[self.index].astype(np.float32)
