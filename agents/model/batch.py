"""Random batches in the agent's TensorDict layout, for smoke tests and benchmarks.

The layout itself (keys, shapes) is documented in :mod:`.dust_model`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from dust_rl.keys import BATCH_ACTION_CHUNK_KEY, BATCH_STATE_KEY, COND_TOKENS_KEY, FUTURE_TOKENS_KEY

from ..config import DustConfig


def random_batch(
    config: DustConfig, batch_size: int, n_cond_tokens: int = 40, generator: torch.Generator | None = None
) -> TensorDict:
    """Standard-normal stand-ins for cached features, with every action present and unpadded.

    Args:
        config: gives the shapes.
        batch_size: B.
        n_cond_tokens: Nc.
        generator: random source.

    Returns:
        TensorDict [B] with ``cond_tokens``, ``state``, ``action_chunk`` and ``future_tokens``.
    """

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(batch_size, *shape, generator=generator)

    return TensorDict(
        {
            COND_TOKENS_KEY: randn(n_cond_tokens, config.cond_dim),
            BATCH_STATE_KEY: randn(config.trunk_state_dim),
            BATCH_ACTION_CHUNK_KEY: randn(config.horizon, config.action_dim),
            FUTURE_TOKENS_KEY: randn(config.n_vision_tokens, config.vision_dim),
        },
        batch_size=[batch_size],
    )
