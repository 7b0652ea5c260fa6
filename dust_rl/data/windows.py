"""Training windows over a dataset, in torchrl's VLA layout.

Each window starts at a row ``t`` and holds

* the observation at ``t`` (``("observation", "image", cam)`` uint8 ``[C, H, W]``,
  ``("observation", "state")``, ...) and its ``language_instruction``;
* ``("vla_action", "chunk")`` ``[horizon, action_dim]``: the actions of rows
  ``t .. t+horizon-1``; past the episode's end the last action is repeated and
  ``action_is_pad`` ``[horizon]`` is True there (torchrl's ``ActionChunkTransform``
  convention);
* ``("future", ...)``: the observation at ``t + future_offset``, the world-model
  target. Past the episode's last stored row it is clamped to that row, flagged by
  ``("future", "is_clamped")``. The last stored row is the observation *before* the
  final action: the terminal observation is not stored.

Random windows come from a torchrl replay buffer over the memmap rows (every row
equally likely); :meth:`DemoWindows.iterate` visits every row once, in order,
e.g. to cache frozen-backbone features.

A note on ``SliceSampler``: in torchrl 0.14.1, ``SliceSampler(pad_output=True,
span=(False, True))`` returns some slices with no real step at all (all-False
mask, about 5% on short episodes) and an integer ``span`` raises, so it cannot
produce end-of-episode windows reliably. Windows are therefore built here from
the episode boundaries: row ``t``'s window reads rows ``min(t + k, end - 1)``.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorDictReplayBuffer, TensorStorage
from torchrl.data.replay_buffers.samplers import RandomSampler, SamplerWithoutReplacement

from dust_rl.keys import ACTION_CHUNK_KEY, ACTION_IS_PAD_KEY, EXPERT_ACTION_KEY, FUTURE_KEY, IMAGE_KEY

from .dataset import DemoDataset


class DemoWindows:
    """Batches of training windows from a :class:`DemoDataset`.

    Args:
        dataset: the dataset.
        horizon: chunk length ``H``.
        future_offset: rows from ``t`` to the future observation; defaults to ``horizon``
            (the observation right after the chunk, DUST's target).
        batch_size: windows per :meth:`sample`.
        action_key: the per-row action to chunk; ``"expert_action"`` (the expert's label,
            which differs from the executed ``"action"`` only under DART noise).
        replacement: sample rows with replacement (True) or as epochs without (False).
        images: read the camera images; False leaves them out and keeps the remaining (small)
            columns in memory, for training on cached image features.
    """

    def __init__(self, dataset: DemoDataset, horizon: int = 16, future_offset: int | None = None,
                 batch_size: int = 64, action_key: str = EXPERT_ACTION_KEY, replacement: bool = True,
                 images: bool = True) -> None:
        future_offset = horizon if future_offset is None else future_offset
        if horizon < 1 or future_offset < 0:
            raise ValueError(f"need horizon >= 1 and future_offset >= 0, got {horizon} and {future_offset}")
        self.dataset, self.horizon, self.future_offset, self.action_key = dataset, horizon, future_offset, action_key
        self.batch_size = batch_size
        self.data = dataset.data if images else dataset.data.exclude(IMAGE_KEY).to_tensordict()
        sampler = RandomSampler() if replacement else SamplerWithoutReplacement()
        self.buffer = TensorDictReplayBuffer(storage=TensorStorage(self.data), sampler=sampler, batch_size=batch_size)

    def sample(self) -> TensorDict:
        """``batch_size`` windows at random rows."""
        current = self.buffer.sample()
        return self._windows(current.exclude("index"), current.get("index").reshape(-1))

    def iterate(self, batch_size: int | None = None) -> Iterator[TensorDict]:
        """Every row's window exactly once, in row order (deterministic)."""
        step = batch_size or self.batch_size
        for start in range(0, len(self.dataset), step):
            rows = torch.arange(start, min(start + step, len(self.dataset)))
            yield self._windows(self.data[rows], rows)

    def _windows(self, current: TensorDictBase, rows: torch.Tensor) -> TensorDict:
        data = self.data
        last = self.dataset.row_episode_end[rows] - 1
        chunk_rows = rows[:, None] + torch.arange(self.horizon)
        future_rows = rows + self.future_offset
        out = self.dataset.with_instructions(current)
        out.set("index", rows)
        out.set(ACTION_CHUNK_KEY, data.get(self.action_key)[torch.minimum(chunk_rows, last[:, None])])
        out.set(ACTION_IS_PAD_KEY, chunk_rows > last[:, None])
        future = data[torch.minimum(future_rows, last)].select("observation")
        future.update({"index": torch.minimum(future_rows, last), "is_clamped": future_rows > last})
        out.set(FUTURE_KEY, future)
        return out
