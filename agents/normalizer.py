"""Standardisation of state and actions with dataset statistics, stored with the policy.

Flow matching starts from unit Gaussian noise, so the trunk sees state and
actions standardised per dimension; the chunk it samples is mapped back to
env units. The statistics are buffers, so they travel in the policy's
checkpoint and a policy never runs with stats other than those it was trained with.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

MIN_STD = 1e-3  # dimensions that never vary (std 0) would otherwise blow up


class Normalizer(nn.Module):
    """Per-dimension (x - mean) / std for state and actions.

    Args:
        state_dim: size of the state vector.
        action_dim: size of one action.
    """

    def __init__(self, state_dim: int, action_dim: int) -> None:
        super().__init__()
        self.register_buffer("state_mean", torch.zeros(state_dim))
        self.register_buffer("state_std", torch.ones(state_dim))
        self.register_buffer("action_mean", torch.zeros(action_dim))
        self.register_buffer("action_std", torch.ones(action_dim))

    @torch.no_grad()
    def set_stats(self, stats: Mapping[str, Mapping[str, Sequence[float]]]) -> None:
        """Load ``{"state": {"mean", "std"}, "action": {"mean", "std"}}`` (lists or tensors)."""
        for name in ("state", "action"):
            for field in ("mean", "std"):
                buffer = getattr(self, f"{name}_{field}")
                value = torch.as_tensor(stats[name][field], dtype=buffer.dtype)
                if value.shape != buffer.shape:
                    raise ValueError(f"{name} {field} has shape {tuple(value.shape)}, expected {tuple(buffer.shape)}")
                buffer.copy_(value.clamp_min(MIN_STD) if field == "std" else value)

    def stats(self) -> dict[str, dict[str, list[float]]]:
        """The statistics in :meth:`set_stats` form."""
        return {name: {field: getattr(self, f"{name}_{field}").tolist() for field in ("mean", "std")}
                for name in ("state", "action")}

    def normalize_state(self, state: Tensor) -> Tensor:
        return (state - self.state_mean) / self.state_std

    def normalize_action(self, action: Tensor) -> Tensor:
        return (action - self.action_mean) / self.action_std

    def denormalize_action(self, action: Tensor) -> Tensor:
        return action * self.action_std + self.action_mean
