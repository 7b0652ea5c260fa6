"""Action-free episodes in training: ``dust-rl train --data.video-dataset DIR``.

DUST's loss takes samples without actions (``has_action = False``): their
action tokens are pure noise at tau_A = 0 and left out of the action loss,
so they train the world-model stream (and the shared trunk) on how scenes
evolve, marginalised over actions; the paper pretrains on action-free video
this way. Here the "video" is another dataset of the same robot and cameras
(other tasks, or demonstrations whose actions are not to be trusted): its
frames, states and instructions are used, its actions dropped. Each training
batch then holds ``video_fraction`` of such windows beside the
demonstrations. Another robot's video would need its own state token; it is
refused with a message.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from dust_rl.keys import ACTION_IS_PAD_KEY, BATCH_ACTION_CHUNK_KEY, BATCH_STATE_KEY, HAS_ACTION_KEY
from dust_rl.train.dataset_batches import DatasetBatches


class ActionFreeBatches(DatasetBatches):
    """Feature batches of a dataset's windows with the actions dropped (``has_action`` False); arguments and
    errors as :class:`~dust_rl.train.dataset_batches.DatasetBatches`."""

    def sample(self) -> TensorDict:
        """A feature batch whose actions are zeros, marked absent (``has_action`` False, every step padded)."""
        batch = super().sample()
        chunk = batch.get(BATCH_ACTION_CHUNK_KEY)
        batch.set(BATCH_ACTION_CHUNK_KEY, torch.zeros_like(chunk))
        batch.set(ACTION_IS_PAD_KEY, torch.ones(chunk.shape[:-1], dtype=torch.bool, device=chunk.device))
        return batch.set(HAS_ACTION_KEY, torch.zeros(chunk.shape[0], dtype=torch.bool, device=chunk.device))


def with_action_free(batch: TensorDict, action_free: TensorDict) -> TensorDict:
    """The demonstrations' ``batch`` (``has_action`` True) and the ``action_free`` rows, in one batch."""
    device = batch.get(BATCH_STATE_KEY).device
    batch.set(HAS_ACTION_KEY, torch.ones(batch.batch_size[0], dtype=torch.bool, device=device))
    return torch.cat([batch, action_free.select(*batch.keys(include_nested=True, leaves_only=True))])
