"""What the RL fine-tuning envs share: a dust-rl env, a frozen DUST policy, and an observation SB3 accepts.

RL on top of an imitation policy (:mod:`dust_rl.rl.steering`, :mod:`dust_rl.rl.residual`) keeps the policy's
weights and changes only what it is fed or what is added to its output, so the base policy stays
recoverable. Both envs show the RL agent the same observation: the robot state and the frozen backbone
features the policy itself conditions on, pooled per camera, plus the pooled instruction (SB3 cannot take
the instruction's text). The state entry is ``robot_state``: torchrl's ``GymWrapper`` renames an entry
called ``state``. Both restart the policy's sampling noise from the reset seed, as evaluation does,
so an episode repeats bit for bit.

The envs serve SB3's training only. The closed-loop comparisons (``dust-rl finetune``'s rows and learning curve)
run the trained agent through ``dust-rl eval``'s runner instead (:mod:`dust_rl.evaluate.closed_loop`), as a torchrl
policy each env builds (:meth:`FrozenPolicyEnv.closed_loop_actor`); :class:`AgentView` builds the agent's
observation for both, so the agent sees the same either way, and the base policy is the evaluated one.

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

import dataclasses
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from dust_rl.agents import DustPolicy, pooled_text
from dust_rl.agents.execution import episode_generator
from dust_rl.keys import INSTRUCTION_KEY, STATE_KEY, flat_name

STATE_NAME = flat_name(STATE_KEY)

Act = Callable[[dict[str, np.ndarray]], np.ndarray]
"""An RL agent as the closed-loop runner asks it: its action for one observation (SB3's deterministic ``predict``,
or a fixed action)."""


def observation_td(obs: dict) -> TensorDict:
    """A dust-rl gymnasium observation as the TensorDict a :class:`~dust_rl.agents.DustPolicy` plans from."""
    td = TensorDict({k: torch.as_tensor(v) for k, v in obs.items() if isinstance(v, np.ndarray)})
    return td.set_non_tensor(INSTRUCTION_KEY, obs[INSTRUCTION_KEY])


def agent_action(action: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """An RL agent's ``action`` as float32 in [-1, 1] (clipped).

    Raises:
        ValueError: the action does not have ``shape`` or holds NaN or infinity.
    """
    action = np.asarray(action, dtype=np.float32)
    if action.shape != shape:
        raise ValueError(f"the action must have shape {shape}, got {action.shape}")
    if not np.isfinite(action).all():
        raise ValueError("the action holds NaN or infinity")
    return np.clip(action, -1.0, 1.0)


@dataclasses.dataclass(frozen=True, eq=False)
class AgentView:
    """The RL agent's observation of a frozen policy's input (the module doc's table), for the envs and the
    closed-loop runner's actors alike.

    Args:
        policy: the frozen policy.
        state_space: the env's robot state space.
        time_limit: with ``finite_horizon``, the env's time limit in steps (``time_left`` is observed); else None.
        base_action_space: the env's action space, when the base action about to be executed is observed
            (residual).
        world_model: also observe the predicted future of the chunk being executed (residual).
    """

    policy: DustPolicy
    state_space: spaces.Box
    time_limit: int | None = None
    base_action_space: spaces.Box | None = None
    world_model: bool = False

    @property
    def space(self) -> spaces.Dict:
        """The observation space."""
        config = self.policy.config
        n_features = len(self.policy.cameras) * config.vision_dim + self.policy.backbone.text_dim
        entries = {"robot_state": self.state_space,
                   "features": spaces.Box(-np.inf, np.inf, (n_features,), np.float32)}
        if config.aux_state_dim:
            entries["object_estimate"] = spaces.Box(-np.inf, np.inf, (config.aux_state_dim,), np.float32)
        if self.time_limit is not None:
            entries["time_left"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        if self.base_action_space is not None:
            entries["base_action"] = self.base_action_space
        if self.world_model:
            size = config.n_vision_tokens * config.vision_dim
            entries["predicted_future"] = spaces.Box(-np.inf, np.inf, (size,), np.float32)
        return spaces.Dict(entries)

    @property
    def reads_steps(self) -> bool:
        """Whether the observation depends on the env steps since the reset (``time_left``)."""
        return self.time_limit is not None

    def __call__(self, features: TensorDictBase, state: np.ndarray, steps: int,
                 base_action: np.ndarray | None = None, future: torch.Tensor | None = None) -> dict[str, np.ndarray]:
        """The observation of one env.

        Args:
            features: the policy's feature batch [1] of the observation (``observation_features``).
            state: the robot state [Ds] in env units.
            steps: env steps since the reset.
            base_action: the base action about to be executed [Da] (a view with ``base_action_space``).
            future: the future tokens [N_o, Dv] (or [1, N_o, Dv]) sampled with the chunk being executed, in the
                encoder's units (a view with ``world_model``).
        """
        image = self.policy.normalizer.normalize_vision(features.get("image_tokens")).mean(2).flatten(1)
        text = pooled_text(features.get("text_tokens"), features.get("text_mask"))
        seen = {"robot_state": np.asarray(state, dtype=np.float32),
                "features": torch.cat([image, text], dim=-1)[0].cpu().numpy().astype(np.float32)}
        if self.policy.config.aux_state_dim:
            seen["object_estimate"] = self.policy.estimate_env_state(features)[0].cpu().numpy().astype(np.float32)
        if self.time_limit is not None:
            seen["time_left"] = np.array([max(0.0, 1.0 - steps / self.time_limit)], np.float32)
        if self.base_action_space is not None:
            seen["base_action"] = np.asarray(base_action, dtype=np.float32)
        if self.world_model:
            standardised = self.policy.standardised_future(future).flatten()
            seen["predicted_future"] = standardised.cpu().numpy().astype(np.float32)
        return seen


class FrozenPolicyEnv(gym.Env):
    """Base of the fine-tuning envs: subclasses set ``action_space`` and implement ``step`` and
    :meth:`closed_loop_actor`.

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
        self.finite_horizon = finite_horizon
        self.view = AgentView(policy, env.observation_space[STATE_NAME],
                              env.unwrapped.max_episode_steps if finite_horizon else None)
        self.observation_space = self.view.space
        self.features: TensorDict | None = None  # of the newest observation, for the next plan
        self.generator = episode_generator(0)
        self.executed: list[np.ndarray] = []  # the env actions of the current episode
        self.predicted_future: torch.Tensor | None = None  # of the newest plan
        self.env_steps = 0  # env steps of every episode so far (RL steps differ when one step runs a chunk)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env; the policy's sampling noise restarts from ``seed`` too (as the seeded
        :class:`~dust_rl.agents.ChunkExecutor` of evaluation restarts it: the same draws)."""
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
        """``action`` as float32 in [-1, 1] (clipped; :func:`agent_action`).

        Raises:
            ValueError: the action has the wrong shape or holds NaN or infinity.
            RuntimeError: ``step`` before ``reset``.
        """
        action = agent_action(action, self.action_space.shape)
        if self.features is None:
            raise RuntimeError("call reset() before step()")
        return action

    def observe(self, obs: dict) -> dict:
        """The RL agent's view of ``obs`` (and its features, kept for the next plan)."""
        self.features = self.policy.observation_features(observation_td(obs))
        return self.view(self.features, obs[STATE_NAME], len(self.executed), *self.next_action())

    def next_action(self) -> tuple[np.ndarray | None, torch.Tensor | None]:
        """The base action about to be executed and the future planned with it, for a view that shows them
        (:mod:`dust_rl.rl.residual`); None here."""
        return None, None

    def closed_loop_actor(self, act: Act) -> TensorDictModuleBase:
        """The torchrl policy that acts, in ``dust-rl eval``'s runner, as this env's agent ``act`` does in its steps
        (an env with ``is_init``, ``episode_seed`` and, when the view reads it, ``step_count``:
        :func:`~dust_rl.evaluate.closed_loop.eval_collector`)."""
        raise NotImplementedError

    def plan(self, action_noise: torch.Tensor | None = None) -> torch.Tensor:
        """The policy's chunk [H, Da] (on the CPU) for the newest observation, from the episode's noise generator.

        The future DUST sampled with it, in the encoder's units [1, N_o, Dv], is kept in :attr:`predicted_future`
        (None when the policy predicts none).
        """
        if action_noise is not None:
            action_noise = action_noise.to(self.policy.weights_device)
        out = self.policy.plan_features(self.features, self.generator, action_noise)
        self.predicted_future = out.get("future_tokens", None)
        return out.get("action_chunk")[0].cpu()

    def close(self) -> None:
        self.env.close()
