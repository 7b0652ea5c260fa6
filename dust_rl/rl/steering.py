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

:class:`SteeredPolicy` is the same steering as a torchrl policy: at each re-plan of the
:class:`~dust_rl.agents.ChunkExecutor` around it, the agent picks the noise from the observation the env
would have shown it, scaled the env's way (:func:`steering_noise`), so the closed-loop comparisons run
through ``dust-rl eval``'s runner with the agent in place.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from dust_rl.agents import ChunkExecutor, DustPolicy
from dust_rl.envs import arguments
from dust_rl.keys import SEED_KEY, STATE_KEY, STEP_KEY
from dust_rl.rl.frozen_policy_env import Act, AgentView, FrozenPolicyEnv, agent_action


def steering_noise(action: np.ndarray, noise_bound: float, chunk_shape: tuple[int, int]) -> torch.Tensor:
    """The initial action noise [1, H, Da] of a checked steering ``action`` in [-1, 1]^(H * Da) (row-major)."""
    return torch.from_numpy(action * noise_bound).view(1, *chunk_shape)


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
        return self._execute(self.plan(steering_noise(self.check_action(action), self.noise_bound, self.chunk_shape)))

    def closed_loop_actor(self, act: Act) -> ChunkExecutor:
        """:class:`SteeredPolicy` with this env's view and bound, re-planning every ``execute_steps`` steps, its
        noise restarted from each episode's seed (the base policy itself is ``policy.executor(seeded=True)``)."""
        return ChunkExecutor(SteeredPolicy(self.policy, self.view, act, self.noise_bound), self.execute_steps,
                             SEED_KEY)

    def _execute(self, chunk: torch.Tensor) -> tuple[dict, float, bool, bool, dict]:
        total, terminated, truncated, info = 0.0, False, False, {}
        for i, env_action in enumerate(chunk[:self.execute_steps].numpy()):
            obs, reward, terminated, truncated, info = self.env_step(env_action)
            total += self.step_discount ** i * float(reward)
            if terminated or truncated:
                break
        return self.observe(obs), total, terminated, truncated, info


class SteeredPolicy(TensorDictModuleBase):
    """A frozen DUST policy whose initial action noise an RL agent picks at each plan: :class:`NoiseSteeringEnv`'s
    step as a torchrl policy, for a :class:`~dust_rl.agents.ChunkExecutor` to wrap as it wraps the policy.

    It reads what the policy reads (and ``step_count`` when the view shows the time left), encodes the observation
    once for the agent's view and the plan, and writes what the policy writes.

    Args:
        policy: the frozen policy.
        view: the agent's observation (:class:`~dust_rl.rl.frozen_policy_env.AgentView`, the env's).
        act: the agent: its action in [-1, 1]^(H * Da) for an observation.
        noise_bound: the largest noise magnitude an action of +-1 maps to.
    """

    def __init__(self, policy: DustPolicy, view: AgentView, act: Act, noise_bound: float) -> None:
        super().__init__()
        self.policy, self.view, self.act, self.noise_bound = policy.eval(), view, act, noise_bound
        self.chunk_size, self.writes_future = policy.chunk_size, policy.writes_future
        self.chunk_shape = (policy.config.horizon, policy.config.action_dim)
        self.in_keys = [*policy.in_keys, *([STEP_KEY] if view.reads_steps else [])]
        self.out_keys = list(policy.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Plan each observation of ``tensordict`` (a batch of one) with the noise the agent picks for it.

        Raises:
            ValueError: more than one observation, or the agent's action has the wrong shape or is not finite.
        """
        if tensordict.numel() != 1:
            raise ValueError(f"a steered policy acts in one env at a time, got a batch of {tuple(tensordict.shape)}")
        features = self.policy.observation_features(tensordict)
        state = self.policy.canonical_view(tensordict).get(STATE_KEY).reshape(-1).cpu().numpy()
        steps = int(tensordict.get(STEP_KEY)) if self.view.reads_steps else 0
        action = agent_action(self.act(self.view(features, state, steps)), (int(np.prod(self.chunk_shape)),))
        noise = steering_noise(action, self.noise_bound, self.chunk_shape).to(self.policy.weights_device)
        planned = self.policy.plan_features(features, action_noise=noise).reshape(tensordict.batch_size)
        return self.policy.write_plan(tensordict, planned)
