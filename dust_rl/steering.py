"""Noise-space steering (DSRL-style): an RL actor picks the initial action noise of a frozen DUST policy.

DUST's sampler is deterministic given its initial noise, so the noise is an
action space in which every point maps to a chunk the imitation policy
considers likely. An RL agent that chooses it improves a frozen policy
without touching its weights (Wagenmaker et al. 2025, "Steering Your
Diffusion Policy with Latent Space Reinforcement Learning"), and the base
policy stays recoverable: the noise the policy would have drawn itself gives
exactly its own chunk.

:class:`NoiseSteeringEnv` is a gymnasium env around a dust-rl env and a
frozen :class:`~dust_rl.agents.DustPolicy`: its action is that noise, scaled
from [-1, 1] to ``[-noise_bound, noise_bound]`` (a standard normal draw lies
within +-2 for 95% of its entries); one step samples a chunk from it and
executes the chunk's first ``execute_steps`` actions, summing their rewards.
Its observation is what a critic needs and SB3 accepts (no text): the robot
state and the frozen backbone features the policy itself conditions on,
pooled per camera, plus the pooled instruction. Any SB3 algorithm with
``MultiInputPolicy`` runs on it unchanged.

======================  =====================  ===================================================
space                   shape                  meaning
======================  =====================  ===================================================
action                  [H * Da] in [-1, 1]    initial action noise / ``noise_bound``, row-major
observation ``state``   [Ds]                   the robot state (``observation.state``)
observation ``features``  [C * Dv + Dt]        per camera the mean of its normalised frozen tokens,
                                               then the mean of the instruction's tokens
======================  =====================  ===================================================
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from dust_rl.agents import DustPolicy, pooled_text
from dust_rl.keys import INSTRUCTION_KEY, STATE_KEY, flat_name
from dust_rl.rollout_video import episode_generator

STATE_NAME = flat_name(STATE_KEY)


class NoiseSteeringEnv(gym.Env):
    """A dust-rl env whose action is a frozen DUST policy's initial action noise; one step runs one chunk.

    Args:
        env: a dust-rl gymnasium env in image mode (the policy's cameras, state and instruction).
        policy: the frozen policy (its weights are never changed here).
        noise_bound: the largest noise magnitude an action of +-1 maps to.
        execute_steps: env steps per chunk; default: the policy's own.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: gym.Env, policy: DustPolicy, noise_bound: float = 2.0,
                 execute_steps: int | None = None) -> None:
        if not (np.isfinite(noise_bound) and noise_bound > 0):
            raise ValueError(f"noise_bound must be a positive number, got {noise_bound}")
        self.env, self.policy, self.noise_bound = env, policy.eval(), float(noise_bound)
        self.execute_steps = execute_steps or policy.execute_steps
        if not 1 <= self.execute_steps <= policy.config.horizon:
            raise ValueError(f"execute_steps must be in [1, {policy.config.horizon}], got {self.execute_steps}")
        self.chunk_shape = (policy.config.horizon, policy.config.action_dim)
        self.action_space = spaces.Box(-1.0, 1.0, (int(np.prod(self.chunk_shape)),), np.float32)
        n_features = len(policy.cameras) * policy.config.vision_dim + policy.backbone.text_dim
        self.observation_space = spaces.Dict({
            "state": env.observation_space[STATE_NAME],
            "features": spaces.Box(-np.inf, np.inf, (n_features,), np.float32),
        })
        self._features: TensorDict | None = None
        self._generator = episode_generator(0)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env; the policy's vision noise restarts from ``seed`` too, so episodes repeat bit for bit."""
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._generator = episode_generator(seed)
        return self._observe(obs), info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Sample a chunk from the noise ``action`` and execute its first ``execute_steps`` actions.

        Raises:
            ValueError: the action has the wrong shape or holds NaN or infinity.
            RuntimeError: ``step`` before ``reset``.
        """
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"the steering action must have shape {self.action_space.shape} (H * Da noise "
                             f"entries), got {action.shape}")
        if not np.isfinite(action).all():
            raise ValueError("the steering action holds NaN or infinity")
        if self._features is None:
            raise RuntimeError("call reset() before step()")
        noise = torch.from_numpy(np.clip(action, -1.0, 1.0) * self.noise_bound).view(1, *self.chunk_shape)
        chunk = self.policy.plan_features(self._features, self._generator, noise).get("action_chunk")[0]
        total, terminated, truncated, info = 0.0, False, False, {}
        for env_action in chunk[:self.execute_steps].numpy():
            obs, reward, terminated, truncated, info = self.env.step(env_action)
            total += float(reward)
            if terminated or truncated:
                break
        return self._observe(obs), total, terminated, truncated, info

    def _observe(self, obs: dict) -> dict:
        """The critic's view of ``obs``; keeps its features for the next chunk's planning."""
        td = TensorDict({k: torch.as_tensor(v) for k, v in obs.items() if isinstance(v, np.ndarray)})
        td.set_non_tensor(INSTRUCTION_KEY, obs[INSTRUCTION_KEY])
        self._features = self.policy.observation_features(td)
        image = self.policy.normalizer.normalize_vision(self._features.get("image_tokens")).mean(2).flatten(1)
        text = pooled_text(self._features.get("text_tokens"), self._features.get("text_mask"))
        features = torch.cat([image, text], dim=-1)[0].numpy().astype(np.float32)
        return {"state": np.asarray(obs[STATE_NAME], dtype=np.float32), "features": features}

    def close(self) -> None:
        self.env.close()
