"""Several noise-steering envs stepped as one: one plan call and one encoder call per step for all of them.

Steering's cost per RL step is the frozen policy's (the encoders on each observation, the sampler on each chunk), and
both take a batch for little more than one (:func:`~dust_rl.rl.steering.steer`); the simulators step one after
another in this process. DSRL collects with several envs per update for the same reason. Two front-ends step
the same :class:`~dust_rl.rl.steering.NoiseSteeringEnv` instances:

- :class:`SB3SteeringVecEnv`, stable-baselines3's ``VecEnv`` (SB3's ``DummyVecEnv`` with a batched
  ``step_wait``): a finished env is reset at once, its last observation in ``terminal_observation`` and
  ``TimeLimit.truncated`` set as ``DummyVecEnv`` sets them, and its episode's return and length in
  ``episode``, as SB3's ``Monitor`` reports them.
- :class:`GymSteeringVectorEnv`, a gymnasium ``VectorEnv`` without auto-reset (``AutoresetMode.DISABLED``): the
  form torchrl's ``GymWrapper`` takes as a batched env, resetting the finished envs itself through ``reset_mask``
  (:mod:`dust_rl.rl.torchrl_sac`).

Each env keeps its own episode (its seed, step count and time limit); seeds given to a reset go to env i as
``seed + i``, as SB3 and gymnasium number them. The envs share one policy and one kind of view and steering.
"""

from __future__ import annotations

import copy
import time

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env import DummyVecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from dust_rl.agents import ChunkExecutor
from dust_rl.rl.frozen_policy_env import Act, observe_batch
from dust_rl.rl.steering import NoiseSteeringEnv, steer


def reset_envs(envs: list[NoiseSteeringEnv], seeds: list[int | None]) -> list[dict]:
    """Reset each env with its seed; their observations, encoded in one call."""
    if not envs:
        return []
    observations = [env.reset_unobserved(seed=seed)[0] for env, seed in zip(envs, seeds, strict=True)]
    return observe_batch(envs, observations)


def checked_actions(envs: list[NoiseSteeringEnv], actions: np.ndarray) -> np.ndarray:
    """Each env's action checked (:meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.check_action`), stacked."""
    if len(actions) != len(envs):
        raise ValueError(f"one action per env: {len(envs)} envs, got {len(actions)} actions")
    return np.stack([env.check_action(action) for env, action in zip(envs, actions)])


class SteeringEnvs:
    """What both front-ends share: the envs, their steering, env steps and closed-loop actor."""

    def __init__(self, envs: list[NoiseSteeringEnv]) -> None:
        if not envs:
            raise ValueError("at least one env is needed")
        self.envs, self.steering = envs, envs[0].steering
        self.steps_before = 0  # env steps of earlier processes (a resumed run)

    @property
    def env_steps(self) -> int:
        """Env steps of every env's episodes so far (with a resumed run's before them)."""
        return self.steps_before + sum(env.env_steps for env in self.envs)

    @env_steps.setter
    def env_steps(self, steps: int) -> None:
        self.steps_before = steps - sum(env.env_steps for env in self.envs)

    def closed_loop_actor(self, act: Act) -> ChunkExecutor:
        """The envs' closed-loop actor (:meth:`~dust_rl.rl.steering.NoiseSteeringEnv.closed_loop_actor`)."""
        return self.envs[0].closed_loop_actor(act)


class SB3SteeringVecEnv(SteeringEnvs, DummyVecEnv):
    """Steering envs as an SB3 ``VecEnv`` (module doc).

    Args:
        envs: steering envs sharing one policy (not yet reset).
    """

    def __init__(self, envs: list[NoiseSteeringEnv]) -> None:
        SteeringEnvs.__init__(self, envs)
        DummyVecEnv.__init__(self, [lambda env=env: env for env in envs])
        self.returns, self.lengths = np.zeros(len(envs)), np.zeros(len(envs), dtype=int)
        self.started = time.time()

    def reset(self) -> VecEnvObs:
        for i, seen in enumerate(reset_envs(self.envs, list(self._seeds))):
            self._save_obs(i, seen)
        self._reset_seeds()
        self._reset_options()
        self.returns[:], self.lengths[:] = 0.0, 0
        return self._obs_from_buf()

    def step_wait(self) -> VecEnvStepReturn:
        finished = []
        for i, (seen, reward, terminated, truncated, info) in enumerate(steer(self.envs, checked_actions(
                self.envs, self.actions))):
            self.buf_rews[i], self.buf_dones[i] = reward, terminated or truncated
            self.returns[i] += reward
            self.lengths[i] += 1
            info = {**info, "TimeLimit.truncated": truncated and not terminated}
            if self.buf_dones[i]:
                info |= {"terminal_observation": seen, "episode": {
                    "r": float(self.returns[i]), "l": int(self.lengths[i]), "t": round(time.time() - self.started, 6)}}
                self.returns[i], self.lengths[i] = 0.0, 0
                finished.append(i)
            else:
                self._save_obs(i, seen)
            self.buf_infos[i] = info
        for i, seen in zip(finished, reset_envs([self.envs[i] for i in finished], [None] * len(finished))):
            self._save_obs(i, seen)
        return self._obs_from_buf(), np.copy(self.buf_rews), np.copy(self.buf_dones), copy.deepcopy(self.buf_infos)


class GymSteeringVectorEnv(SteeringEnvs, VectorEnv):
    """Steering envs as a gymnasium ``VectorEnv`` without auto-reset, for torchrl's ``GymWrapper`` (module doc).

    Args:
        envs: steering envs sharing one policy (not yet reset).
    """

    def __init__(self, envs: list[NoiseSteeringEnv]) -> None:
        SteeringEnvs.__init__(self, envs)
        self.num_envs = len(envs)
        self.autoreset_mode = AutoresetMode.DISABLED
        self.metadata = {"autoreset_mode": AutoresetMode.DISABLED}
        self.single_observation_space, self.single_action_space = envs[0].observation_space, envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observations: list[dict] = [{} for _ in envs]

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """Reset the envs ``options["reset_mask"]`` selects (default: all), env i with ``seed + i`` (or
        ``seed[i]``)."""
        mask = np.asarray((options or {}).get("reset_mask", np.ones(self.num_envs, bool)), bool)
        seeds = ([None if seed is None else seed + i for i in range(self.num_envs)] if not isinstance(seed, list)
                 else seed)
        chosen = [int(i) for i in np.flatnonzero(mask)]
        for i, seen in zip(chosen, reset_envs([self.envs[i] for i in chosen], [seeds[i] for i in chosen])):
            self.observations[i] = seen
        return self._stacked(), {}

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict]:
        """Step every env; a finished one must be reset (``reset_mask``) before the next step."""
        results = steer(self.envs, checked_actions(self.envs, actions))
        self.observations = [seen for seen, *_ in results]
        rewards, terminated, truncated = (np.array([r[k] for r in results]) for k in (1, 2, 3))
        success = np.array([bool(r[4]["is_success"]) for r in results])
        return (self._stacked(), rewards.astype(np.float64), terminated.astype(bool), truncated.astype(bool),
                {"is_success": success, "_is_success": np.ones(self.num_envs, bool)})

    def close(self, **kwargs) -> None:
        for env in self.envs:
            env.close()

    def _stacked(self) -> dict[str, np.ndarray]:
        return {name: np.stack([seen[name] for seen in self.observations]) for name in self.single_observation_space}
