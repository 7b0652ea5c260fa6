"""The language instruction's observation space: a ``Text`` space that survives ``AsyncVectorEnv``'s shared memory.

``AsyncVectorEnv`` (shared memory on, its default) reads its observation buffers once, when it starts,
and hands out views that the workers overwrite. A ``Text`` space is decoded into Python strings in
that one read, so every later observation showed the empty buffer decoded (256 ``'a'``) instead of the
instruction. :class:`InstructionText` reads the shared buffer when the observation is used instead:
the vector env deep-copies its observations before returning them (its default ``copy=True``), and
that copy is a tuple of the current strings; with ``copy=False`` the sequence decodes on indexing.
Everything else (sampling, ``contains``, sync vector envs, torchrl's spec conversion) is ``Text``'s.

Where strings cannot go (torchrl's batched ``GymEnv``, collectors' shared buffers), the instruction travels as
zero-padded UTF-8 bytes instead (:func:`encode_instruction`).
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector.utils import read_from_shared_memory

MAX_INSTRUCTION_LENGTH = 256  # characters
INSTRUCTION_BYTES = 4 * MAX_INSTRUCTION_LENGTH  # UTF-8 takes at most 4 bytes a character


def encode_instruction(text: str) -> np.ndarray:
    """``text`` as zero-padded UTF-8 bytes (uint8 ``[INSTRUCTION_BYTES]``)."""
    raw = text.encode()
    if len(raw) > INSTRUCTION_BYTES:
        raise ValueError(f"instruction of {len(raw)} UTF-8 bytes, more than {INSTRUCTION_BYTES}: {text[:60]!r}...")
    return np.frombuffer(raw.ljust(INSTRUCTION_BYTES, b"\0"), dtype=np.uint8)


def decode_instruction(data: np.ndarray | torch.Tensor) -> str:
    """The string :func:`encode_instruction` encoded."""
    return bytes(np.asarray(data, dtype=np.uint8)).rstrip(b"\0").decode()


def instruction_bytes_space() -> gym.spaces.Box:
    """The space of :func:`encode_instruction`'s arrays."""
    return gym.spaces.Box(0, 255, (INSTRUCTION_BYTES,), np.uint8)


class InstructionText(gym.spaces.Text):
    """A ``gym.spaces.Text`` whose shared-memory copy in ``AsyncVectorEnv`` is decoded on use, not once."""


class SharedTexts(Sequence):
    """The ``n`` strings in a vector env's shared ``Text`` buffer, decoded when read (a deep copy: a tuple)."""

    def __init__(self, space: gym.spaces.Text, shared_memory, n: int) -> None:
        self.space, self.shared_memory, self.n = space, shared_memory, n

    def _decoded(self) -> tuple[str, ...]:
        return read_from_shared_memory.dispatch(gym.spaces.Text)(self.space, self.shared_memory, self.n)

    def __getitem__(self, index):
        return self._decoded()[index]

    def __len__(self) -> int:
        return self.n

    def __eq__(self, other: object) -> bool:
        return tuple(self) == (tuple(other) if isinstance(other, Sequence) else other)

    def __repr__(self) -> str:
        return repr(self._decoded())

    def __deepcopy__(self, memo: dict) -> tuple[str, ...]:
        return self._decoded()


@read_from_shared_memory.register(InstructionText)
def _read_instructions(space: InstructionText, shared_memory, n: int = 1) -> SharedTexts:
    return SharedTexts(space, shared_memory, n)
