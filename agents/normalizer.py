"""Standardisation of state, actions and image tokens with dataset statistics, stored with the policy.

Flow matching starts from unit Gaussian noise, so the trunk sees state,
actions and frozen image tokens (condition and world-model target)
standardised per dimension; the chunk it samples is mapped back to env units
and the future it predicts back to the encoder's units. Image-token
statistics matter for pretrained encoders: EfficientNet-Lite features have
per-channel means up to +-10 and standard deviations of 4-12 on our frames.

The world-model target is standardised a second time, after pooling to the
vision grid (``future_mean``, ``future_std``): averaging standardised tokens
down to a coarser grid leaves per-channel variances well below one (Lite0's
8x8 pooled to 4x4 on press_button: 0.16-0.78), which would make ``lambda_wm``
weigh a coarse target less than a fine one. With unit-variance targets the
per-element loss means the same at every grid.
The statistics are buffers, so they travel in the policy's
checkpoint and a policy never runs with stats other than those it was trained with.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor, nn

MIN_STD = 1e-3  # dimensions that never vary (std 0) would otherwise blow up


class Normalizer(nn.Module):
    """Per-dimension (x - mean) / std for state and actions.

    Args:
        state_dim: size of the state vector.
        action_dim: size of one action.
        vision_dim: size of one image token (identity statistics until :meth:`set_vision_stats`).
    """

    # Buffers that policy files written before they existed lack (identity then).
    FUTURE_STATS = ("future_mean", "future_std")  # the world-model target's standardisation after pooling
    OPTIONAL_BUFFERS = ("vision_mean", "vision_std", "future_change_scale", *FUTURE_STATS)
    # The scales (standard deviations) the statistics divide by: at least MIN_STD as the setters write them.
    SCALES = ("vision_std", "future_std", "future_change_scale", "state_std", "action_std")

    def __init__(self, state_dim: int, action_dim: int, vision_dim: int) -> None:
        super().__init__()
        self.register_buffer("vision_mean", torch.zeros(vision_dim))
        self.register_buffer("vision_std", torch.ones(vision_dim))
        # Per channel, of the standardised tokens pooled to the world-model target's grid (module doc)
        self.register_buffer("future_mean", torch.zeros(vision_dim))
        self.register_buffer("future_std", torch.ones(vision_dim))
        # RMS of the standardised future's change over H steps (a ``future_target="change"`` policy's target unit)
        self.register_buffer("future_change_scale", torch.ones(()))
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

    @torch.no_grad()
    def set_vision_stats(self, tokens: Tensor) -> None:
        """Per-channel statistics of image tokens [..., vision_dim] (e.g. every cached token of the dataset)."""
        rows = max(1, (1 << 16) * tokens.shape[0] // max(1, tokens.numel() // tokens.shape[-1]))
        self._set_moments("vision", tokens.split(rows))  # about 65,536 tokens per chunk

    @torch.no_grad()
    def set_future_stats(self, targets: Iterable[Tensor]) -> None:
        """Per-channel statistics of world-model targets, given in chunks [..., vision_dim] of standardised tokens
        pooled to the vision grid (every row of the dataset)."""
        self._set_moments("future", targets)

    def _set_moments(self, name: str, chunks: Iterable[Tensor]) -> None:
        """``<name>_mean`` and ``<name>_std`` from float64 sums over ``chunks`` (the cache may be float16, large,
        memory-mapped)."""
        size = self.vision_mean.shape[0]
        total = square = None  # on the chunks' device
        n = 0
        for chunk in chunks:
            if chunk.shape[-1] != size:
                raise ValueError(f"need tokens of size {size}, got shape {tuple(chunk.shape)}")
            chunk = chunk.reshape(-1, size).double()
            total = chunk.sum(0) if total is None else total + chunk.sum(0)
            square = chunk.square().sum(0) if square is None else square + chunk.square().sum(0)
            n += len(chunk)
        if n < 2:
            raise ValueError(f"need >= 2 tokens of size {size} for the {name} statistics, got {n}")
        mean = total / n
        var = (square / n - mean.square()).clamp_min(0.0) * n / (n - 1)
        getattr(self, f"{name}_mean").copy_(mean)
        getattr(self, f"{name}_std").copy_(var.sqrt().clamp_min(MIN_STD))

    @torch.no_grad()
    def set_future_change_scale(self, rms: float) -> None:
        """The unit of a change target: the root mean square of the standardised changes over the dataset (one
        scale for every channel, so channels that barely move are not blown up into noise to model)."""
        if not (math.isfinite(rms) and rms > 0):
            raise ValueError(f"the future's change scale must be a positive finite number, got {rms!r}")
        self.future_change_scale.fill_(max(rms, MIN_STD))

    def normalize_vision(self, tokens: Tensor) -> Tensor:
        return (tokens.float() - self.vision_mean) / self.vision_std

    def denormalize_vision(self, tokens: Tensor) -> Tensor:
        return tokens * self.vision_std + self.vision_mean

    def standardise_future(self, pooled: Tensor) -> Tensor:
        """Standardised tokens pooled to the vision grid -> the world-model target's units (module doc)."""
        return (pooled - self.future_mean) / self.future_std

    def unstandardise_future(self, target: Tensor) -> Tensor:
        return target * self.future_std + self.future_mean

    def normalize_state(self, state: Tensor) -> Tensor:
        return (state - self.state_mean) / self.state_std

    def normalize_action(self, action: Tensor) -> Tensor:
        return (action - self.action_mean) / self.action_std

    def denormalize_action(self, action: Tensor) -> Tensor:
        return action * self.action_std + self.action_mean
