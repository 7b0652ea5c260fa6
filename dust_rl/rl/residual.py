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

:class:`ResidualCorrection` is the same correction as a torchrl module after the base policy's
:class:`~dust_rl.agents.ChunkExecutor`, so the closed-loop comparisons run through ``dust-rl eval``'s
runner: the agent sees what the env would show it and its action is added the env's way
(:func:`corrected_action`).
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from dust_rl.agents import ChunkExecutor, DustPolicy
from dust_rl.agents.execution import replans
from dust_rl.keys import ACTION_KEY, PREDICTED_FUTURE_KEY, SEED_KEY, STATE_KEY, STEP_KEY
from dust_rl.rl.frozen_policy_env import Act, AgentView, FrozenPolicyEnv, agent_action


def corrected_action(base_action: np.ndarray, action: np.ndarray, residual_scale: np.ndarray,
                     box: spaces.Box) -> np.ndarray:
    """The executed action: ``base_action`` plus ``residual_scale`` times a checked agent ``action``, clipped to
    the env's action ``box``."""
    return np.clip(base_action + action * residual_scale, box.low, box.high)


class ResidualEnv(FrozenPolicyEnv):
    """A dust-rl env whose action is added, scaled, to a frozen DUST policy's next action.

    Args:
        env: a dust-rl gymnasium env in image mode.
        policy: the frozen policy.
        residual_scale: per action dimension, what an RL action of +-1 adds (a number or [Da]); default 10% of
            the action box's half-width.
        execute_steps: actions executed per chunk before the policy re-plans; default: the policy's own.
        world_model: also observe the predicted future of the chunk being executed (module doc).
        finite_horizon, reward_penalty: see :class:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv`.

    Raises:
        ValueError: ``world_model`` with a policy that predicts no future (the action-only variant or sampler).
    """

    def __init__(self, env: gym.Env, policy: DustPolicy, residual_scale: float | np.ndarray | None = None,
                 execute_steps: int | None = None, world_model: bool = False, finite_horizon: bool = False,
                 reward_penalty: bool = False) -> None:
        super().__init__(env, policy, execute_steps, finite_horizon, reward_penalty=reward_penalty)
        if world_model and policy.config.sampler_name == "action_only":
            raise ValueError(f"world_model needs a policy that predicts the future; this one (variant "
                             f"{policy.config.variant!r}, sampler {policy.config.sampler_name!r}) does not")
        low, high = env.action_space.low, env.action_space.high
        scale = 0.1 * (high - low) / 2 if residual_scale is None else residual_scale
        self.residual_scale = np.broadcast_to(np.asarray(scale, dtype=np.float32), low.shape).copy()
        if not (np.isfinite(self.residual_scale).all() and (self.residual_scale >= 0).all()):
            raise ValueError(f"residual_scale must be finite and >= 0, got {residual_scale}")
        self.action_space = spaces.Box(-1.0, 1.0, low.shape, np.float32)
        self.view = dataclasses.replace(self.view, base_action_space=env.action_space, world_model=world_model)
        self.observation_space = self.view.space
        self.chunk, self.index = None, 0

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Execute the base action plus ``residual_scale * action``, clipped to the action box.

        Raises:
            ValueError, RuntimeError: see :meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.check_action`.
        """
        executed = corrected_action(self.base_action, self.check_action(action), self.residual_scale,
                                    self.env.action_space)
        reward, terminated, truncated, info = self.env_step(executed)
        self.index += 1
        return self.observe(self.observation()), self.rl_reward(reward, info), terminated, truncated, info

    def next_action(self) -> tuple[np.ndarray, torch.Tensor | None]:
        """Re-plan at the reset and when the chunk's executed part is used up (the evaluation's rule); the next base
        action and the future planned with its chunk."""
        if replans(len(self.executed), self.execute_steps):
            self.chunk, self.index = self.plan().numpy(), 0
        return self.base_action, self.predicted_future

    def closed_loop_actor(self, act: Act) -> TensorDictSequential:
        """The base policy's seeded :class:`~dust_rl.agents.ChunkExecutor` (re-planning every ``execute_steps``
        steps), then :class:`ResidualCorrection` with this env's view, scale and action box."""
        return TensorDictSequential(ChunkExecutor(self.policy, self.execute_steps, SEED_KEY),
                                    ResidualCorrection(self.view, act, self.residual_scale))

    @property
    def base_action(self) -> np.ndarray:
        """The action the base policy executes next."""
        return self.chunk[self.index].astype(np.float32)


class ResidualCorrection(TensorDictModuleBase):
    """After the base policy's :class:`~dust_rl.agents.ChunkExecutor`, add an RL agent's correction to the action it
    is about to execute: :class:`ResidualEnv`'s step as a torchrl module, run at every step.

    It reads the observation, the executor's ``action`` (and ``PREDICTED_FUTURE_KEY`` with ``world_model``;
    ``step_count`` when the view shows the time left) and overwrites ``action``.

    Args:
        view: the agent's observation (:class:`~dust_rl.rl.frozen_policy_env.AgentView`, the env's: with
            ``base_action_space``, the env's action box).
        act: the agent: its action in [-1, 1]^Da for an observation.
        residual_scale: per action dimension, what an agent action of +-1 adds [Da].
    """

    def __init__(self, view: AgentView, act: Act, residual_scale: np.ndarray) -> None:
        super().__init__()
        if view.base_action_space is None:
            raise ValueError("a residual correction needs a view of the base action (AgentView.base_action_space)")
        self.view, self.act, self.residual_scale = view, act, residual_scale
        self.policy = view.policy
        self.in_keys = [*self.policy.in_keys, ACTION_KEY, *([PREDICTED_FUTURE_KEY] if view.world_model else []),
                        *([STEP_KEY] if view.reads_steps else [])]
        self.out_keys = [ACTION_KEY]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Correct the action of the one env of ``tensordict`` (unbatched, or a batch of one).

        Raises:
            ValueError: more than one env, or the agent's action has the wrong shape or is not finite.
        """
        if tensordict.numel() != 1:
            raise ValueError(f"a residual correction acts in one env at a time, got a batch of "
                             f"{tuple(tensordict.shape)}")
        base = tensordict.get(ACTION_KEY)
        base_action = base.reshape(-1).cpu().numpy()
        future = tensordict.get(PREDICTED_FUTURE_KEY) if self.view.world_model else None
        state = self.policy.canonical_view(tensordict).get(STATE_KEY).reshape(-1).cpu().numpy()
        steps = int(tensordict.get(STEP_KEY)) if self.view.reads_steps else 0
        seen = self.view(self.policy.observation_features(tensordict), state, steps, base_action, future)
        executed = corrected_action(base_action, agent_action(self.act(seen), base_action.shape), self.residual_scale,
                                    self.view.base_action_space)
        return tensordict.set(ACTION_KEY, torch.from_numpy(executed).to(base.device).reshape(base.shape))
