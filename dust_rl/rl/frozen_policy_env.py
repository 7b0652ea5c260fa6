"""What the RL fine-tuning envs share: a dust-rl env, a frozen DUST policy, and an observation SB3 accepts.

RL on top of an imitation policy (:mod:`dust_rl.rl.steering`, :mod:`dust_rl.rl.residual`) keeps the policy's
weights and changes only what it is fed or what is added to its output, so the base policy stays
recoverable. Both envs show the RL agent the same observation: the robot state and the frozen backbone
features the policy itself conditions on, pooled per camera, plus the pooled instruction (SB3 cannot take
the instruction's text). The state entry is ``robot_state``: torchrl's ``GymWrapper`` renames an entry
called ``state``. Both restart the policy's sampling noise from the reset seed, as evaluation does,
so an episode repeats bit for bit.

========================  =================  ===================================================
observation               shape              meaning
========================  =================  ===================================================
``robot_state``           [Ds]               the robot state (``observation.state``)
``features``              [C * Dv + Dt]      per camera the mean of its normalised frozen tokens,
                                             then the mean of the instruction's tokens
``object_estimate``       [S]                only for a policy with a state read-out
                                             (``--policy.lambda-aux``): its estimate of the
                                             normalised object state, where the mean-pooled
                                             features no longer say where a small object is
``predicted_future``      [N_o * Dv]         residual with ``world_model`` only
                                             (:mod:`dust_rl.rl.residual`)
``time_left``             [1]                with ``finite_horizon`` only: the fraction of the
                                             episode's time limit still to run
========================  =================  ===================================================

``finite_horizon`` makes the time limit part of the RL task. By default a time-limit end is a truncation, which
SB3 bootstraps past as if the episode went on; with a sparse reward for success within the limit, the critic
then values a failing state by what the policy might reach after the limit, and on stack its Q sat at the top
of the returns everywhere (BENCHMARKS "Headroom for noise steering on stack"). With ``finite_horizon`` the
limit ends the episode as terminated, a failure worth 0 (so does the env's other truncation, an infeasible IK
problem or diverging physics), and the observation says how much time is left, so the value of a state can
depend on it (Pardo et al. 2018, "Time limits in reinforcement learning").
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from dust_rl.agents import DustPolicy, pooled_text
from dust_rl.agents.execution import episode_generator
from dust_rl.keys import INSTRUCTION_KEY, STATE_KEY, flat_name

STATE_NAME = flat_name(STATE_KEY)


def observation_td(obs: dict) -> TensorDict:
    """A dust-rl gymnasium observation as the TensorDict a :class:`~dust_rl.agents.DustPolicy` plans from."""
    td = TensorDict({k: torch.as_tensor(v) for k, v in obs.items() if isinstance(v, np.ndarray)})
    return td.set_non_tensor(INSTRUCTION_KEY, obs[INSTRUCTION_KEY])


class FrozenPolicyEnv(gym.Env):
    """Base of the fine-tuning envs: subclasses set ``action_space`` and implement ``step``.

    Args:
        env: a dust-rl gymnasium env in image mode (the policy's cameras, state and instruction).
        policy: the frozen policy (put in eval mode; its weights are never changed here).
        execute_steps: env steps per chunk; default: the policy's own.
        finite_horizon: a time-limit end is terminated, not truncated, and ``time_left`` is observed (module doc).
    """

    metadata = {"render_modes": []}

    def __init__(self, env: gym.Env, policy: DustPolicy, execute_steps: int | None = None,
                 finite_horizon: bool = False) -> None:
        self.env, self.policy = env, policy.eval()
        self.execute_steps = execute_steps or policy.execute_steps
        if not 1 <= self.execute_steps <= policy.config.horizon:
            raise ValueError(f"execute_steps must be in [1, {policy.config.horizon}], got {self.execute_steps}")
        n_features = len(policy.cameras) * policy.config.vision_dim + policy.backbone.text_dim
        entries = {"robot_state": env.observation_space[STATE_NAME],
                   "features": spaces.Box(-np.inf, np.inf, (n_features,), np.float32)}
        if policy.config.aux_state_dim:
            entries["object_estimate"] = spaces.Box(-np.inf, np.inf, (policy.config.aux_state_dim,), np.float32)
        self.finite_horizon = finite_horizon
        if finite_horizon:
            entries["time_left"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        self.observation_space = spaces.Dict(entries)
        self.features: TensorDict | None = None  # of the newest observation, for the next plan
        self.generator = episode_generator(0)
        self.executed: list[np.ndarray] = []  # the env actions of the current episode
        self.predicted_future: np.ndarray | None = None  # of the newest plan
        self.env_steps = 0  # env steps of every episode so far (RL steps differ when one step runs a chunk)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env; the policy's sampling noise restarts from ``seed`` too."""
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self.generator = episode_generator(seed)
        self.executed = []
        return self.observe(obs), info

    def env_step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """One step of the wrapped env, recorded in :attr:`executed`."""
        action = np.asarray(action, dtype=np.float32)
        self.executed.append(action)
        self.env_steps += 1
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self.finite_horizon and truncated:
            terminated, truncated = True, False
        return obs, reward, terminated, truncated, info

    def check_action(self, action: np.ndarray) -> np.ndarray:
        """``action`` as float32 in [-1, 1] (clipped).

        Raises:
            ValueError: the action has the wrong shape or holds NaN or infinity.
            RuntimeError: ``step`` before ``reset``.
        """
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"the action must have shape {self.action_space.shape}, got {action.shape}")
        if not np.isfinite(action).all():
            raise ValueError("the action holds NaN or infinity")
        if self.features is None:
            raise RuntimeError("call reset() before step()")
        return np.clip(action, -1.0, 1.0)

    def observe(self, obs: dict) -> dict:
        """The RL agent's view of ``obs`` (and its features, kept for the next plan)."""
        self.features = self.policy.observation_features(observation_td(obs))
        image = self.policy.normalizer.normalize_vision(self.features.get("image_tokens")).mean(2).flatten(1)
        text = pooled_text(self.features.get("text_tokens"), self.features.get("text_mask"))
        features = torch.cat([image, text], dim=-1)[0].cpu().numpy().astype(np.float32)
        seen = {"robot_state": np.asarray(obs[STATE_NAME], dtype=np.float32), "features": features}
        if "object_estimate" in self.observation_space.spaces:
            seen["object_estimate"] = self.policy.estimate_env_state(self.features)[0].cpu().numpy().astype(np.float32)
        if self.finite_horizon:
            limit = self.env.unwrapped.max_episode_steps
            seen["time_left"] = np.array([max(0.0, 1.0 - len(self.executed) / limit)], np.float32)
        return seen

    def step_base(self) -> tuple[dict, float, bool, bool, dict]:
        """One step in which the base policy acts as it would alone (the RL agent's "off" action)."""
        raise NotImplementedError

    def plan(self, action_noise: torch.Tensor | None = None) -> torch.Tensor:
        """The policy's chunk [H, Da] (on the CPU) for the newest observation, from the episode's noise generator.

        The future DUST sampled with it, normalised and flattened [N_o * Dv], is kept in :attr:`predicted_future`
        (None when the policy predicts none).
        """
        if action_noise is not None:
            action_noise = action_noise.to(self.policy.weights_device)
        out = self.policy.plan_features(self.features, self.generator, action_noise)
        future = out.get("future_tokens", None)
        self.predicted_future = (None if future is None else
                                 self.policy.standardised_future(future)[0].flatten().cpu().numpy())
        return out.get("action_chunk")[0].cpu()

    def close(self) -> None:
        self.env.close()
