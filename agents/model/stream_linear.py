"""Per-stream linear layers batched into one matmul."""

from __future__ import annotations

import torch
from torch import Tensor, nn

ALL_STREAMS = slice(None)


class StreamLinear(nn.Module):
    """One linear layer per stream, applied to all streams in one batched matmul.

    ``weight[s]`` and ``bias[s]`` act on stream ``s`` only; initialised like
    ``nn.Linear`` (uniform in +-1/sqrt(d_in)).

    Args:
        n_streams: S.
        d_in: input width.
        d_out: output width.
    """

    def __init__(self, n_streams: int, d_in: int, d_out: int) -> None:
        super().__init__()
        bound = d_in**-0.5
        self.weight = nn.Parameter(torch.empty(n_streams, d_in, d_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(n_streams, 1, d_out).uniform_(-bound, bound))

    def forward(self, x: Tensor, streams: slice = ALL_STREAMS) -> Tensor:
        """Map [S', ..., d_in] to [S', ..., d_out], S' being the ``streams`` selected from S."""
        if streams == ALL_STREAMS:
            weight, bias = self.weight, self.bias
        else:
            weight, bias = self.weight[streams], self.bias[streams]
        shape = x.shape
        return torch.baddbmm(bias, x.reshape(shape[0], -1, shape[-1]), weight).view(*shape[:-1], -1)
