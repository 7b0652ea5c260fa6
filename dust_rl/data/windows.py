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

``start_rows`` / ``start_fraction`` draw a fixed share of each batch from the
first rows of the episodes. Why: where to go is decided at the first frame (the
arm is at home; only the cameras and the instruction say which object and where),
and from then on the arm's own motion gives most of the answer away. Drawn
uniformly, an 80-step episode's first row is 1 window in 80: on pick_place with
2,000 demos a trained policy's first 8-step move missed the expert's by 15 cm
(chance) while moving on from step 8 was within 1.4 cm, and a small attention
head on the same frozen tokens fitted the first move to 1.2 cm
(``experiments/first_move_error.py``, ``experiments/first_move_probe.py``). Measured:
a quarter of each batch from the first 4 rows lowered that 15 cm to 13 cm
only (docs/franka_results.md), so rarity was not the main cause.

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
        start_rows: how many rows at the start of every episode ``start_fraction`` applies to (0: none).
        start_fraction: expected share of each batch drawn from those rows (with replacement);
            the rest comes uniformly from the other rows.
    """

    def __init__(self, dataset: DemoDataset, horizon: int = 16, future_offset: int | None = None,
                 batch_size: int = 64, action_key: str = EXPERT_ACTION_KEY, replacement: bool = True,
                 images: bool = True, start_rows: int = 0, start_fraction: float = 0.0) -> None:
        future_offset = horizon if future_offset is None else future_offset
        if horizon < 1 or future_offset < 0:
            raise ValueError(f"need horizon >= 1 and future_offset >= 0, got {horizon} and {future_offset}")
        if start_rows < 0 or not 0 <= start_fraction < 1 or bool(start_rows) != bool(start_fraction):
            raise ValueError(f"need start_rows >= 0 and start_fraction in [0, 1), both zero or both set; got "
                             f"{start_rows} and {start_fraction}")
        if start_rows and not replacement:
            raise ValueError("start_rows weights the draw of rows: it needs replacement=True")
        self.dataset, self.horizon, self.future_offset, self.action_key = dataset, horizon, future_offset, action_key
        self.batch_size = batch_size
        self.data = dataset.data if images else dataset.data.exclude(IMAGE_KEY).to_tensordict()
        sampler = RandomSampler() if replacement else SamplerWithoutReplacement()
        self.buffer = TensorDictReplayBuffer(storage=TensorStorage(self.data), sampler=sampler, batch_size=batch_size)
        self.row_weights = self._row_weights(start_rows, start_fraction) if start_rows else None

    def _row_weights(self, start_rows: int, start_fraction: float) -> torch.Tensor:
        """Per row, its probability of being drawn."""
        step = torch.arange(len(self.dataset)) - torch.repeat_interleave(self.dataset.episode_starts,
                                                                         self.dataset.lengths)
        is_start = step < start_rows
        if is_start.all():
            raise ValueError(f"start_rows={start_rows} covers every row of every episode; nothing is left to weight")
        return torch.where(is_start, start_fraction / is_start.sum(), (1 - start_fraction) / (~is_start).sum())

    def sample(self) -> TensorDict:
        """``batch_size`` windows at random rows (torch's global generator)."""
        if self.row_weights is not None:
            rows = torch.multinomial(self.row_weights, self.batch_size, replacement=True)
            return self._windows(self.data[rows], rows)
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
