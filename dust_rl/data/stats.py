"""Normalisation statistics of the numeric dataset entries (state, actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from dust_rl.keys import ACTION_KEY, ENV_STATE_KEY, EXPERT_ACTION_KEY, STATE_KEY, flat_name

STAT_KEYS = (STATE_KEY, ENV_STATE_KEY, ACTION_KEY, EXPERT_ACTION_KEY)


def compute_stats(rows: TensorDictBase) -> dict[str, dict[str, list[float]]]:
    """Per-dimension mean, std, min, max and count of each entry in :data:`STAT_KEYS` present in ``rows``."""
    stats = {}
    for key in STAT_KEYS:
        if key not in rows.keys(include_nested=True):
            continue
        values = rows.get(key).to(torch.float64).reshape(rows.shape[0], -1)
        if not values.shape[1]:  # e.g. no privileged state in an imported dataset
            continue
        stats[flat_name(key)] = {
            "mean": values.mean(0).tolist(), "std": values.std(0, correction=0).tolist(),
            "min": values.min(0).values.tolist(), "max": values.max(0).values.tolist(),
            "count": [values.shape[0]],
        }
    return stats
