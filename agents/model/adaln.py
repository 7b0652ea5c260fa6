"""AdaLN-zero modulation: each stream's timestep embedding becomes its shift/scale/gate vectors."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .stream_linear import StreamLinear


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """AdaLN: parameter-free LayerNorm, then per-sample (or per-token) scale and shift."""
    return torch.addcmul(shift, F.layer_norm(x, x.shape[-1:]), scale)


class Modulation(nn.Module):
    """AdaLN-zero: per stream, one zero-initialised linear map from that stream's
    timestep embedding to all the shift/scale/gate vectors of its blocks.

    One matmul serves every block (batch-1 latency is set by op count). Scale
    slots get a constant +1, so at initialisation every scale is 1 and every
    shift and gate 0: each block starts as the identity.

    Args:
        n_streams: S; stream s's vectors depend on stream s's conditioning only.
        d_model: width of the conditioning and of each produced vector.
        n_slots: number of produced vectors.
        scale_slots: indices of the slots that act as scales.
    """

    def __init__(self, n_streams: int, d_model: int, n_slots: int, scale_slots: Sequence[int]) -> None:
        super().__init__()
        self.n_slots = n_slots
        self.linear = StreamLinear(n_streams, d_model, n_slots * d_model)
        nn.init.zeros_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)
        offset = torch.zeros(n_slots, d_model)
        offset[list(scale_slots)] = 1.0
        self.register_buffer("offset", offset.flatten(), persistent=False)

    def forward(self, c: Tensor, token_index: Tensor | None = None) -> tuple[Tensor, ...]:
        """Map SiLU'd conditioning [S, B, T, d] to ``n_slots`` tensors [S, B, T, d].

        Args:
            c: conditioning per stream; T = 1 for one vector per sample.
            token_index: optional long [N]; gives token n the modulation of row
                ``token_index[n]`` of ``c`` (output [S, B, N, d]), so that tokens of
                different modalities in one stream get their own timestep.
        """
        m = torch.add(self.linear(c), self.offset)
        if token_index is not None:
            m = m.index_select(2, token_index)
        return m.view(*m.shape[:-1], self.n_slots, -1).unbind(-2)
