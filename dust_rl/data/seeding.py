"""Per-episode seeds: every episode is ``reset(seed=s)`` with a recorded ``s``.

Episodes are identified by (task, seed), so a collection can be resumed, split
across worker processes, or reproduced one episode at a time. Workers share one
ascending sequence of not-yet-known seeds, each taking every ``num_workers``-th,
so no seed runs twice and none is skipped. A policy's sampling noise restarts
from the episode's seed too (:func:`dust_rl.agents.execution.episode_generator`).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator

import gymnasium as gym
import numpy as np

from dust_rl.envs.instruction_space import encode_instruction, instruction_bytes_space
from dust_rl.errors import ConfigError
from dust_rl.keys import INSTRUCTION_BYTES_KEY, INSTRUCTION_KEY, SEED_KEY, SUCCESS_KEY

# The seed ranges every command shares: demonstrations from 0, validation episodes (to choose settings on) from
# VALIDATION_SEED, held-out episodes (to report) from HELDOUT_SEED.
VALIDATION_SEED = 5000
HELDOUT_SEED = 10_000
MAX_SEED = int(np.iinfo(np.int64).max)  # episodes record their seed as an int64 (EpisodeSeedWrapper, episode.json)


def check_seeds(first: int, count: int, flag: str = "--seed") -> None:
    """Raise :class:`ConfigError` unless the ``count`` episode seeds from ``first`` on fit in [0, MAX_SEED].

    Why: each episode's seed is stored as an int64, so a larger one fails at the first reset, deep inside a worker.
    """
    if not 0 <= first <= MAX_SEED - count + 1:
        raise ConfigError(f"{flag} {first}: the {count} episode seeds from it must fit in [0, {MAX_SEED}] (an "
                          f"episode's seed is stored as an int64); give {flag} in [0, {MAX_SEED - count + 1}]")


@dataclasses.dataclass(frozen=True)
class SeedSchedule:
    """The seeds one worker runs: the `worker`-th of every `num_workers` unknown seeds from `start`.

    Picklable, so it travels to collector worker processes inside the env constructor.
    """

    start: int = 0
    known: frozenset[int] = frozenset()
    worker: int = 0
    num_workers: int = 1

    def __iter__(self) -> Iterator[int]:
        unknown = (s for s in itertools.count(self.start) if s not in self.known)
        return itertools.islice(unknown, self.worker, None, self.num_workers)


class EpisodeSeedWrapper(gym.Wrapper):
    """Resets from a seed schedule and reports the seed, instruction and success flag as observations.

    A torchrl collector resets without a seed; this wrapper supplies the next seed of
    its schedule (an explicit ``reset(seed=...)`` still wins) and adds ``"episode_seed"``
    (int64 ``[1]``), ``"instruction_utf8"`` (:func:`encode_instruction`) and ``"is_success"``
    (``info["is_success"]``, int8 ``[1]``) to every observation, so all three land in the
    collected TensorDicts, from worker processes too.
    """

    def __init__(self, env: gym.Env, schedule: SeedSchedule) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({
            **env.observation_space.spaces,
            SEED_KEY: gym.spaces.Box(0, np.iinfo(np.int64).max, (1,), np.int64),
            INSTRUCTION_BYTES_KEY: instruction_bytes_space(),
            SUCCESS_KEY: gym.spaces.MultiBinary(1),
        })
        self._seeds = iter(schedule)
        self._seed = 0
        self._instruction = encode_instruction("")

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self._seed = next(self._seeds) if seed is None else int(seed)
        obs, info = self.env.reset(seed=self._seed, options=options)
        text = obs.get(INSTRUCTION_KEY, info.get(INSTRUCTION_KEY, ""))  # rgb mode / state mode / none
        self._instruction = encode_instruction(text)
        return self._observation(obs, info), info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._observation(obs, info), reward, terminated, truncated, info

    def _observation(self, obs: dict, info: dict) -> dict:
        return {**obs, SEED_KEY: np.array([self._seed], dtype=np.int64), INSTRUCTION_BYTES_KEY: self._instruction,
                SUCCESS_KEY: np.array([bool(info["is_success"])], dtype=np.int8)}
