"""Embeddings of the DUST trunk: flow time, token positions, stream encoders/decoders."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import TIME_FREQ_DIM
from .adaln import modulate
from .stream_linear import StreamLinear


def frequencies(dim: int, max_period: float = 10000.0) -> Tensor:
    """Geometric frequencies 1 ... 1/max_period for ``dim // 2`` sin-cos pairs."""
    half = dim // 2
    return torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32) / half)


def sincos(values: Tensor, freqs: Tensor) -> Tensor:
    """Sin-cos features [..., 2 * len(freqs)] of real ``values`` [...]."""
    args = values.float()[..., None] * freqs
    return torch.cat([args.sin(), args.cos()], dim=-1)


def sincos_positions_1d(n: int, dim: int) -> Tensor:
    """Fixed positions [n, dim] for a token sequence (action chunk)."""
    return sincos(torch.arange(n), frequencies(dim))


def sincos_positions_2d(rows: int, cols: int, dim: int) -> Tensor:
    """Fixed positions [rows*cols, dim] for a row-major token grid (vision).

    Half the channels encode the row, half the column, so neighbouring grid
    cells get similar codes along both axes.
    """
    r, c = torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij")
    freqs = frequencies(dim // 2)
    return torch.cat([sincos(r.flatten(), freqs), sincos(c.flatten(), freqs)], dim=-1)


def mlp(dims: Sequence[int]) -> nn.Sequential:
    """Linear layers through ``dims`` with SiLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        if i:
            layers.append(nn.SiLU())
        layers.append(nn.Linear(d_in, d_out))
    return nn.Sequential(*layers)


class TimestepEmbedder(nn.Module):
    """Flow time tau in [0, 1] -> conditioning vector for AdaLN, with separate weights per stream.

    tau is scaled by 1000 before the sinusoid so that the usual DiT frequency
    range separates the small steps of a few-step sampler.

    Args:
        n_streams: S.
        d_model: output width.
        freq_dim: size of the sinusoidal features.
        scale: factor applied to tau before the sinusoid.
    """

    def __init__(self, n_streams: int, d_model: int, freq_dim: int = TIME_FREQ_DIM, scale: float = 1000.0) -> None:
        super().__init__()
        self.register_buffer("freqs", frequencies(freq_dim) * scale, persistent=False)
        self.fc1 = StreamLinear(n_streams, freq_dim, d_model)
        self.fc2 = StreamLinear(n_streams, d_model, d_model)

    def forward(self, tau: Tensor) -> Tensor:
        """Embed tau [S, B, T] into [S, B, T, d_model] with stream s's weights."""
        return self.fc2(F.silu(self.fc1(sincos(tau, self.freqs))))


class TokenEncoder(nn.Module):
    """Per-token MLP into the trunk width plus fixed positions.

    Actions use one linear layer, vision a 3-layer SiLU MLP (DUST); the
    positions (1D for actions, 2D for the vision grid) are a frozen buffer.
    """

    def __init__(self, dims: Sequence[int], positions: Tensor) -> None:
        super().__init__()
        self.net = mlp(dims)
        self.register_buffer("positions", positions, persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """Map [B, N, D_in] to [B, N, d_model]."""
        return self.net(x) + self.positions


class TokenDecoder(nn.Module):
    """AdaLN-modulated final norm plus a per-token MLP back to the data space.

    The shift and scale come from the trunk's modulation of the token's stream.
    The last layer starts at zero, so an untrained model predicts zero velocity.
    """

    def __init__(self, dims: Sequence[int]) -> None:
        super().__init__()
        self.net = mlp(dims)
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
        """Decode tokens [B, N, d] with AdaLN vectors [B, 1 or N, d]."""
        return self.net(modulate(x, shift, scale))
