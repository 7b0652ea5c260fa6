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
import torch

from dust_rl.envs.env import MAX_INSTRUCTION_LENGTH
from dust_rl.keys import INSTRUCTION_BYTES_KEY, INSTRUCTION_KEY, SEED_KEY, SUCCESS_KEY

INSTRUCTION_BYTES = 4 * MAX_INSTRUCTION_LENGTH  # UTF-8 takes at most 4 bytes a character
# The seed ranges every command shares: demonstrations from 0, validation episodes (to choose settings on) from
# VALIDATION_SEED, held-out episodes (to report) from HELDOUT_SEED.
VALIDATION_SEED = 5000
HELDOUT_SEED = 10_000


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


def encode_instruction(text: str) -> np.ndarray:
    """``text`` as zero-padded UTF-8 bytes (uint8 ``[INSTRUCTION_BYTES]``)."""
    raw = text.encode()
    if len(raw) > INSTRUCTION_BYTES:
        raise ValueError(f"instruction of {len(raw)} UTF-8 bytes, more than {INSTRUCTION_BYTES}: {text[:60]!r}...")
    return np.frombuffer(raw.ljust(INSTRUCTION_BYTES, b"\0"), dtype=np.uint8)


def decode_instruction(data: np.ndarray | torch.Tensor) -> str:
    """The string :func:`encode_instruction` encoded."""
    return bytes(np.asarray(data, dtype=np.uint8)).rstrip(b"\0").decode()


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
            INSTRUCTION_BYTES_KEY: gym.spaces.Box(0, 255, (INSTRUCTION_BYTES,), np.uint8),
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
