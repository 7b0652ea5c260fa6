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
``features``              [C * Dv (+ Dt)]    per camera the mean of its normalised frozen tokens,
                                             then (unless ``instruction`` is off) the mean of the
                                             instruction's tokens
``object_estimate``       [S]                only for a policy with a state read-out
                                             (``--model.lambda-aux``): its estimate of the
                                             normalised object state, where the mean-pooled
                                             features no longer say where a small object is
``predicted_future``      [N_o * Dv]         residual with ``world_model`` only
                                             (:mod:`dust_rl.rl.residual`)
``time_left``             [1]                with ``finite_horizon`` only: the fraction of the
                                             episode's time limit still to run
``object_state``          [S]                with ``object_state`` only, for the critic: the env's
                                             true object state (``observation.environment_state``)
========================  =================  ===================================================

``finite_horizon`` makes the time limit part of the RL task. By default a time-limit end is a truncation, which
SB3 bootstraps past as if the episode went on; with a sparse reward for success within the limit, the critic
then values a failing state by what the policy might reach after the limit, and on stack its Q sat at the top
of the returns everywhere (BENCHMARKS "Headroom for noise steering on stack"). With ``finite_horizon`` the
limit ends the episode as terminated, a failure worth 0 (so does the env's other truncation, an infeasible IK
problem or diverging physics), and the observation says how much time is left, so the value of a state can
depend on it (Pardo et al. 2018, "Time limits in reinforcement learning").

``object_state`` makes the critic asymmetric: it also sees where the objects truly are, which the actor must infer
from the images (the critic serves training only, so privileged information costs nothing at deployment; DSRL's
critics read the low-dimensional state). The actor's networks never read that entry (:attr:`AgentView.actor_view`,
:mod:`dust_rl.rl.asymmetric`), so the closed-loop actor acts from what the policy sees. ``reward_penalty`` pays -1
per RL step and 0 on the step that succeeds (DSRL's reward): the return counts the steps to success, so a faster
success is worth more, where a sparse 0/1 reward discounted per chunk barely tells them apart.

Each step executes its actions without rendering (``DustEnv.step_unobserved``) and renders once, after the last:
a steering step executes a chunk, and only its end is observed. :func:`observe_batch` encodes the observations of
several envs in one call of the frozen encoders (:mod:`dust_rl.rl.vector` steps many envs at once).
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
from dust_rl.keys import (
    BATCH_ACTION_CHUNK_KEY,
    ENV_STATE_KEY,
    FUTURE_TOKENS_KEY,
    IMAGE_TOKENS_KEY,
    INSTRUCTION_KEY,
    STATE_KEY,
    TEXT_MASK_KEY,
    TEXT_TOKENS_KEY,
    flat_name,
)

STATE_NAME = flat_name(STATE_KEY)
ENV_STATE_NAME = flat_name(ENV_STATE_KEY)
OBJECT_STATE = "object_state"
"""The observation entry of the env's true object state: the critic's alone (:mod:`dust_rl.rl.asymmetric`)."""

Act = Callable[[dict[str, np.ndarray]], np.ndarray]
"""An RL agent as the closed-loop runner asks it: its action for one observation (SB3's deterministic ``predict``,
or a fixed action)."""


def observation_td(obs: dict) -> TensorDict:
    """A dust-rl gymnasium observation as the TensorDict a :class:`~dust_rl.agents.DustPolicy` plans from."""
    td = TensorDict({k: torch.as_tensor(v) for k, v in obs.items() if isinstance(v, np.ndarray)})
    return td.set_non_tensor(INSTRUCTION_KEY, obs[INSTRUCTION_KEY])


def encode(policy: DustPolicy, observations: list[dict]) -> TensorDict:
    """The policy's feature batch [N] of N dust-rl gymnasium observations, in one call of its frozen encoders."""
    return policy.observation_features(torch.stack([observation_td(obs) for obs in observations]))


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
        instruction: the features end with the pooled instruction.
        object_state_space: the env's object state space, when the true object state is observed (for the
            critic only: :attr:`actor_view`).
    """

    policy: DustPolicy
    state_space: spaces.Box
    time_limit: int | None = None
    base_action_space: spaces.Box | None = None
    world_model: bool = False
    instruction: bool = True
    object_state_space: spaces.Box | None = None

    @property
    def actor_view(self) -> AgentView:
        """The view without the critic's privileged entry: what the actor reads, and all a closed-loop actor gets."""
        return dataclasses.replace(self, object_state_space=None)

    @property
    def space(self) -> spaces.Dict:
        """The observation space."""
        config = self.policy.config
        n_features = (len(self.policy.cameras) * config.vision_dim
                      + (self.policy.backbone.text_dim if self.instruction else 0))
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
        if self.object_state_space is not None:
            entries[OBJECT_STATE] = spaces.Box(-np.inf, np.inf, self.object_state_space.shape, np.float32)
        return spaces.Dict(entries)

    @property
    def reads_steps(self) -> bool:
        """Whether the observation depends on the env steps since the reset (``time_left``)."""
        return self.time_limit is not None

    def __call__(self, features: TensorDictBase, state: np.ndarray, steps: int,
                 base_action: np.ndarray | None = None, future: torch.Tensor | None = None) -> dict[str, np.ndarray]:
        """The observation of one env by a view without ``object_state`` (the closed-loop actors'; the envs observe
        theirs with :meth:`batch`).

        Args:
            features: the policy's feature batch [1] of the observation (``observation_features``).
            state: the robot state [Ds] in env units.
            steps: env steps since the reset.
            base_action: the base action about to be executed [Da] (a view with ``base_action_space``).
            future: the future tokens [N_o, Dv] (or [1, N_o, Dv]) sampled with the chunk being executed, in the
                encoder's units (a view with ``world_model``).
        """
        base_actions = None if base_action is None else np.asarray(base_action)[None]
        futures = None if future is None else future.reshape(1, *future.shape[-2:])
        return self.batch(features, np.asarray(state)[None], [steps], base_actions, futures)[0]

    def batch(self, features: TensorDictBase, states: np.ndarray, steps: list[int],
              base_actions: np.ndarray | None = None, futures: torch.Tensor | None = None,
              object_states: np.ndarray | None = None) -> list[dict[str, np.ndarray]]:
        """The observations of N envs, each as :meth:`__call__` gives it, from their feature batch [N] (the
        read-out and the pooling run once for all); the other arguments are theirs stacked ([N, ...], N steps)."""
        pooled = self.policy.normalizer.normalize_vision(features.get(IMAGE_TOKENS_KEY)).mean(2).flatten(1)
        if self.instruction:
            text = pooled_text(features.get(TEXT_TOKENS_KEY), features.get(TEXT_MASK_KEY))
            pooled = torch.cat([pooled, text], dim=-1)
        seen = {"robot_state": np.asarray(states, dtype=np.float32), "features": _numpy(pooled)}
        if self.policy.config.aux_state_dim:
            seen["object_estimate"] = _numpy(self.policy.estimate_env_state(features))
        if self.time_limit is not None:
            seen["time_left"] = np.array([[max(0.0, 1.0 - n / self.time_limit)] for n in steps], np.float32)
        if self.base_action_space is not None:
            seen["base_action"] = np.asarray(base_actions, dtype=np.float32)
        if self.world_model:
            seen["predicted_future"] = _numpy(self.policy.standardised_future(futures).flatten(1))
        if self.object_state_space is not None:
            seen[OBJECT_STATE] = np.asarray(object_states, dtype=np.float32)
        return [{name: value[i] for name, value in seen.items()} for i in range(len(steps))]


def _numpy(values: torch.Tensor) -> np.ndarray:
    return values.cpu().numpy().astype(np.float32)


class FrozenPolicyEnv(gym.Env):
    """Base of the fine-tuning envs: subclasses set ``action_space`` and implement ``step`` and
    :meth:`closed_loop_actor`.

    Args:
        env: a dust-rl gymnasium env in image mode (the policy's cameras, state and instruction).
        policy: the frozen policy (put in eval mode; its weights are never changed here).
        execute_steps: env steps per chunk; default: the policy's own.
        finite_horizon: a time-limit end is terminated, not truncated, and ``time_left`` is observed (module doc).
        instruction: the features end with the pooled instruction (:class:`AgentView`).
        object_state: observe the env's true object state, for an asymmetric critic (module doc).
        reward_penalty: each RL step pays -1, 0 if it succeeds, instead of the env's reward (module doc).
    """

    metadata = {"render_modes": []}

    def __init__(self, env: gym.Env, policy: DustPolicy, execute_steps: int | None = None,
                 finite_horizon: bool = False, *, instruction: bool = True, object_state: bool = False,
                 reward_penalty: bool = False) -> None:
        self.env, self.policy = env, policy.eval()
        self.execute_steps = execute_steps or policy.execute_steps
        if not 1 <= self.execute_steps <= policy.config.horizon:
            raise ValueError(f"execute_steps must be in [1, {policy.config.horizon}], got {self.execute_steps}")
        self.finite_horizon, self.reward_penalty = finite_horizon, reward_penalty
        self.view = AgentView(policy, env.observation_space[STATE_NAME],
                              env.unwrapped.max_episode_steps if finite_horizon else None, instruction=instruction,
                              object_state_space=env.observation_space[ENV_STATE_NAME] if object_state else None)
        self.observation_space = self.view.space
        self.features: TensorDict | None = None  # of the newest observation, for the next plan
        self.generator = episode_generator(0)
        self.executed: list[np.ndarray] = []  # the env actions of the current episode
        self.predicted_future: torch.Tensor | None = None  # of the newest plan
        self.env_steps = 0  # env steps of every episode so far (RL steps differ when one step runs a chunk)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the env; the policy's sampling noise restarts from ``seed`` too (as the seeded
        :class:`~dust_rl.agents.ChunkExecutor` of evaluation restarts it: the same draws)."""
        obs, info = self.reset_unobserved(seed=seed, options=options)
        return self.observe(obs), info

    def reset_unobserved(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """:meth:`reset`, returning the wrapped env's observation, which :func:`observe_batch` then encodes with
        other envs' in one call."""
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self.generator = episode_generator(seed)
        self.executed = []
        return obs, info

    def env_step(self, action: np.ndarray) -> tuple[float, bool, bool, dict]:
        """One step of the wrapped env, recorded in :attr:`executed`, without its observation (nothing is rendered:
        :meth:`observation` renders the state after the last): reward, terminated, truncated, info."""
        action = np.asarray(action, dtype=np.float32)
        self.executed.append(action)
        self.env_steps += 1
        reward, terminated, truncated, info = self.env.unwrapped.step_unobserved(action)
        if self.finite_horizon and truncated:
            terminated, truncated = True, False
        return reward, terminated, truncated, info

    def observation(self) -> dict:
        """The wrapped env's observation of its current state, as its ``step`` would have returned it."""
        return self.env.unwrapped.observe()

    def rl_reward(self, reward: float, info: dict) -> float:
        """The reward of an RL step whose env reward is ``reward`` and whose last env step's info is ``info``: that
        reward, or with ``reward_penalty`` 0 if the step succeeded and -1 otherwise."""
        if not self.reward_penalty:
            return float(reward)
        return 0.0 if info["is_success"] else -1.0

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
        return observe_batch([self], [obs])[0]

    def next_action(self) -> tuple[np.ndarray | None, torch.Tensor | None]:
        """The base action about to be executed and the future planned with it, for a view that shows them
        (:mod:`dust_rl.rl.residual`); None here."""
        return None, None

    def closed_loop_actor(self, act: Act) -> TensorDictModuleBase:
        """The torchrl policy that acts, in ``dust-rl eval``'s runner, as this env's agent ``act`` does in its steps
        (an env with ``is_init``, ``episode_seed`` and, when the view reads it, ``step_count``:
        :func:`~dust_rl.evaluate.closed_loop.eval_collector`)."""
        raise NotImplementedError

    def plan(self) -> torch.Tensor:
        """The policy's chunk [H, Da] (on the CPU) for the newest observation, from the episode's noise generator.

        The future DUST sampled with it, in the encoder's units [1, N_o, Dv], is kept in :attr:`predicted_future`
        (None when the policy predicts none).
        """
        out = self.policy.plan_features(self.features, self.generator)
        self.predicted_future = out.get(FUTURE_TOKENS_KEY, None)
        return out.get(BATCH_ACTION_CHUNK_KEY)[0].cpu()

    def close(self) -> None:
        self.env.close()


def observe_batch(envs: list[FrozenPolicyEnv], observations: list[dict]) -> list[dict]:
    """Each env's :meth:`~FrozenPolicyEnv.observe` of its observation, the frozen encoders and the view run once for
    all (the envs share one policy and one kind of view)."""
    features = encode(envs[0].policy, observations)
    for i, env in enumerate(envs):
        env.features = features[i:i + 1]
    upcoming = [env.next_action() for env in envs]
    view = envs[0].view
    base_actions = np.stack([base for base, _ in upcoming]) if view.base_action_space is not None else None
    futures = torch.cat([future for _, future in upcoming]) if view.world_model else None
    object_states = (np.stack([obs[ENV_STATE_NAME] for obs in observations])
                     if view.object_state_space is not None else None)
    return view.batch(features, np.stack([obs[STATE_NAME] for obs in observations]),
                      [len(env.executed) for env in envs], base_actions, futures, object_states)
