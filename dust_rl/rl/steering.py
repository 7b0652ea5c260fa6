"""Noise-space steering (DSRL-style): an RL actor picks the initial action noise of a frozen DUST policy.

DUST's sampler is deterministic given its initial noises, so the action noise is an action space in which every
point maps to a chunk the imitation policy considers likely. An RL agent that chooses it improves a frozen policy
without touching its weights (Wagenmaker et al. 2025, "Steering Your Diffusion Policy with Latent Space
Reinforcement Learning").

:class:`NoiseSteeringEnv`'s action is a latent in [-1, 1]^D, scaled to ``[-noise_bound, noise_bound]`` and mapped
to the noise [H, Da] (:class:`Steering`): by default the latent is the noise itself (D = H * Da, row-major); with
``latent_dim`` it is lower-dimensional, as DSRL steers (:func:`latent_map`). One step samples a chunk from it and
executes the chunk's first ``execute_steps`` actions, rendering only after the last, and sums their rewards
discounted to the chunk's start by ``step_discount`` per env step: with the env's dense reward shaped for that
discount (``shaping_discount``), a chunk's reward is then potential-based shaping for an agent whose discount per
chunk is ``step_discount ** execute_steps`` (the shaping telescopes within the chunk). Observations:
:mod:`dust_rl.rl.frozen_policy_env`. Any SB3 algorithm with ``MultiInputPolicy`` runs on it unchanged;
:mod:`dust_rl.rl.vector` steps several at once through one plan call (:func:`steer`).

A chunk is a deterministic function of the observation and the latent, for every variant: DUST also starts its
vision stream from noise, and a drawn one would make the same latent give other chunks at other steps (transitions
the critic cannot predict from what it sees). Steering starts the vision stream from one fixed draw instead
(:data:`VISION_NOISE_SEED`). So the base policy, whose vision noise is drawn afresh at each plan, is recovered in
distribution, not draw for draw (exactly only for the action-only variant): the latent 0 is the centre of its action
noise, and :func:`prior_latents` draws latents whose noise has its action noise's distribution.

:class:`SteeredPolicy` is the same steering as a torchrl policy: at each re-plan of the
:class:`~dust_rl.agents.ChunkExecutor` around it, the agent picks the latent from the observation the env
would have shown its actor, mapped the env's way (:class:`Steering`), so the closed-loop comparisons run
through ``dust-rl eval``'s runner with the agent in place.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from dust_rl.agents import ChunkExecutor, DustPolicy
from dust_rl.agents.execution import episode_generator
from dust_rl.agents.model.flow_matching import cpu_drawn
from dust_rl.envs import arguments
from dust_rl.keys import BATCH_ACTION_CHUNK_KEY, SEED_KEY, STATE_KEY, STEP_KEY
from dust_rl.rl.frozen_policy_env import Act, AgentView, FrozenPolicyEnv, agent_action, observe_batch

VISION_NOISE_SEED = 0
"""Seed of the one vision-noise draw every steered plan starts the vision stream from."""
LATENT_MAP_SEED = 0
"""Seed of the random map of a latent whose size is neither Da nor H * Da (:func:`latent_map`)."""


def latent_map(latent_dim: int | None, chunk_shape: tuple[int, int]) -> torch.Tensor | None:
    """The fixed linear map [H * Da, D] from a D-dimensional latent to the flat action noise; None where the latent
    is the noise itself (``latent_dim`` None or H * Da).

    D = Da: every row of the chunk's noise is the latent (pi0's DSRL steers one row repeated over the horizon); any
    other D: a random map with entries drawn from N(0, 1 / D) (:data:`LATENT_MAP_SEED`). Fixed, not learnt: the
    replay buffer's actions must keep meaning the same noise. Either way a latent drawn from N(0, I) gives noise
    entries of variance 1 (the repeat map: each exactly N(0, 1); the random one: on average), the policy's own
    noise distribution entry by entry (:func:`prior_latents`).

    Raises:
        ValueError: ``latent_dim`` not in [1, H * Da].
    """
    horizon, action_dim = chunk_shape
    size = horizon * action_dim
    if latent_dim is None or latent_dim == size:
        return None
    if not 1 <= latent_dim <= size:
        raise ValueError(f"latent_dim must be in [1, {size}] (the noise has H x Da = {horizon} x {action_dim} "
                         f"entries), got {latent_dim}")
    if latent_dim == action_dim:
        return torch.eye(action_dim).repeat(horizon, 1)
    generator = torch.Generator().manual_seed(LATENT_MAP_SEED)
    return torch.randn(size, latent_dim, generator=generator) / latent_dim ** 0.5


def prior_latents(n: int, latent_dim: int, noise_bound: float) -> torch.Tensor:
    """``n`` RL actions [n, D] in [-1, 1] whose latents are drawn from N(0, I) (torch's generator; clipped at the
    bound): through :func:`latent_map` the noise the policy itself would draw, entry by entry (without a latent,
    exactly its distribution up to the clipping). The base policy's own actions, as far as a latent can say, which a
    replay buffer can start from (``dust-rl finetune steer --base-warmup``)."""
    return (torch.randn(n, latent_dim) / noise_bound).clamp(-1.0, 1.0)


@dataclasses.dataclass(frozen=True, eq=False)
class Steering:
    """How an RL action becomes a frozen policy's initial noises, for the envs and the closed-loop actor alike.

    Args:
        noise_bound: the latent an action of +-1 maps to.
        chunk_shape: (H, Da).
        latent_map: :func:`latent_map`'s map, None for the noise itself.
        vision_noise: the fixed initial vision noise [1, N_o, Dv] (module doc); None without a vision stream.
    """

    noise_bound: float
    chunk_shape: tuple[int, int]
    latent_map: torch.Tensor | None
    vision_noise: torch.Tensor | None

    @classmethod
    def of(cls, policy: DustPolicy, noise_bound: float, latent_dim: int | None = None) -> Steering:
        """The steering of ``policy``; ValueError for a bad ``noise_bound`` or ``latent_dim``."""
        if not (np.isfinite(noise_bound) and noise_bound > 0):
            raise ValueError(f"noise_bound must be a positive number, got {noise_bound}")
        config = policy.config
        chunk_shape = (config.horizon, config.action_dim)
        vision = None
        if config.has_vision:
            vision = cpu_drawn(torch.randn, 1, config.n_vision_tokens, config.vision_dim,
                               generator=episode_generator(VISION_NOISE_SEED))
        return cls(float(noise_bound), chunk_shape, latent_map(latent_dim, chunk_shape), vision)

    @property
    def action_dim(self) -> int:
        """D, the size of an RL action."""
        return int(np.prod(self.chunk_shape)) if self.latent_map is None else self.latent_map.shape[1]

    def noise(self, actions: np.ndarray) -> torch.Tensor:
        """The initial action noise [N, H, Da] of checked RL actions [N, D] in [-1, 1]."""
        latent = torch.from_numpy(actions * self.noise_bound)
        flat = latent if self.latent_map is None else latent @ self.latent_map.T
        return flat.view(-1, *self.chunk_shape)

    def plan(self, policy: DustPolicy, features: TensorDictBase, actions: np.ndarray,
             generator: torch.Generator | None = None) -> TensorDict:
        """The policy's plan of a feature batch [N] steered by checked RL actions [N, D]. Nothing is drawn, except
        with an action-only policy (no vision noise to fix): an action noise is drawn from ``generator`` and
        discarded, as without steering."""
        device = policy.weights_device
        vision = None if self.vision_noise is None else self.vision_noise.expand(len(actions), -1, -1).to(device)
        return policy.plan_features(features, generator, self.noise(actions).to(device), vision)


class NoiseSteeringEnv(FrozenPolicyEnv):
    """A dust-rl env whose action is a frozen DUST policy's initial action noise (or a latent of it); one step runs
    one chunk.

    Args:
        env: a dust-rl gymnasium env in image mode.
        policy: the frozen policy.
        noise_bound: the largest latent magnitude an action of +-1 maps to.
        execute_steps: env steps per chunk; default: the policy's own.
        step_discount: per env step, the discount of the rewards within a chunk (module doc); 1: their sum.
        finite_horizon, instruction, object_state, reward_penalty: see
            :class:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv`.
        latent_dim: the size D of the action (:func:`latent_map`); default: the noise itself, H * Da.
    """

    def __init__(self, env: gym.Env, policy: DustPolicy, noise_bound: float = 2.0,
                 execute_steps: int | None = None, step_discount: float = 1.0, finite_horizon: bool = False, *,
                 latent_dim: int | None = None, instruction: bool = True, object_state: bool = False,
                 reward_penalty: bool = False) -> None:
        self.steering = Steering.of(policy, noise_bound, latent_dim)
        super().__init__(env, policy, execute_steps, finite_horizon, instruction=instruction,
                         object_state=object_state, reward_penalty=reward_penalty)
        self.step_discount = arguments.discount("step_discount", step_discount)
        self.action_space = spaces.Box(-1.0, 1.0, (self.steering.action_dim,), np.float32)

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Sample a chunk from the noise ``action`` and execute its first ``execute_steps`` actions.

        Raises:
            ValueError, RuntimeError: see :meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.check_action`.
        """
        return steer([self], self.check_action(action)[None])[0]

    def execute(self, chunk: torch.Tensor) -> tuple[dict, float, bool, bool, dict]:
        """Execute the first ``execute_steps`` actions of ``chunk`` [H, Da] (fewer if the episode ends); the wrapped
        env's observation after the last, the RL step's reward, terminated, truncated and the last step's info."""
        total, terminated, truncated, info = 0.0, False, False, {}
        for i, env_action in enumerate(chunk[:self.execute_steps].numpy()):
            reward, terminated, truncated, info = self.env_step(env_action)
            total += self.step_discount ** i * float(reward)
            if terminated or truncated:
                break
        return self.observation(), self.rl_reward(total, info), terminated, truncated, info

    def closed_loop_actor(self, act: Act) -> ChunkExecutor:
        """:class:`SteeredPolicy` with this env's actor view and steering, re-planning every ``execute_steps``
        steps, its sampling noise restarted from each episode's seed (the base policy itself is
        ``policy.executor(seeded=True)``)."""
        return ChunkExecutor(SteeredPolicy(self.policy, self.view.actor_view, act, self.steering), self.execute_steps,
                             SEED_KEY)


def steer(envs: list[NoiseSteeringEnv], actions: np.ndarray) -> list[tuple[dict, float, bool, bool, dict]]:
    """One step of each env (reset, sharing one policy and steering) with its checked action ([N, D]): one plan call
    for all the chunks and one encoder call for all the next observations; each env's (observation, reward,
    terminated, truncated, info)."""
    first = envs[0]
    features = torch.cat([env.features for env in envs])
    chunks = first.steering.plan(first.policy, features, actions, first.generator).get(BATCH_ACTION_CHUNK_KEY).cpu()
    results = [env.execute(chunk) for env, chunk in zip(envs, chunks, strict=True)]
    views = observe_batch(envs, [obs for obs, *_ in results])
    return [(view, *rest) for view, (_, *rest) in zip(views, results, strict=True)]


class SteeredPolicy(TensorDictModuleBase):
    """A frozen DUST policy whose initial action noise an RL agent picks at each plan: :class:`NoiseSteeringEnv`'s
    step as a torchrl policy, for a :class:`~dust_rl.agents.ChunkExecutor` to wrap as it wraps the policy.

    It reads what the policy reads (and ``step_count`` when the view shows the time left), encodes the observation
    once for the agent's view and the plan, and writes what the policy writes.

    Args:
        policy: the frozen policy.
        view: the agent's observation (:class:`~dust_rl.rl.frozen_policy_env.AgentView`, the env's actor view: no
            privileged entry).
        act: the agent: its action in [-1, 1]^D for an observation.
        steering: how its action becomes the noises (the env's).
    """

    def __init__(self, policy: DustPolicy, view: AgentView, act: Act, steering: Steering) -> None:
        super().__init__()
        self.policy, self.view, self.act, self.steering = policy.eval(), view, act, steering
        self.chunk_size, self.writes_future = policy.chunk_size, policy.writes_future
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
        action = agent_action(self.act(self.view(features, state, steps)), (self.steering.action_dim,))
        planned = self.steering.plan(self.policy, features, action[None]).reshape(tensordict.batch_size)
        return self.policy.write_plan(tensordict, planned)
