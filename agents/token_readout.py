"""A state read-out straight from the frozen image tokens, steered by the instruction.

The keypoint read-out (:mod:`.state_readout`) sees the objects only through
heat-map coordinates. The frozen tokens themselves hold the named cube's
position better: an attention-pooling head fitted on the front camera's
Lite0 stride-8 tokens of fresh pick_place resets reads it to 1.5 cm (tokens
pooled to 8x8) or 0.7 cm (16x16), but only when fitted on 2,000 layouts; on
200 it learns nothing (15.5 cm, predicting the mean; docs/franka_results.md,
``experiments/frozen_feature_probe.py``). So this read-out is meant to be fitted
on rendered frames (``--readout.aux-frames``, ``--readout.warmup-steps``), not on the
demonstrations' few layouts.

It is :class:`~.attention_pooling.AttentionProbe` over every camera's
condition tokens (one position embedding per camera and cell), with the
pooled instruction added to each token before the attention, so which object
is named decides where it looks.

==============  ==================  =====================================
tensor          shape               meaning
==============  ==================  =====================================
image_tokens    [B, C, N, Dv]       standardised condition tokens per camera
text_tokens     [B, L, Dt]          instruction tokens (mask [B, L])
estimate        [B, S]              normalised environment state
==============  ==================  =====================================
"""

from __future__ import annotations

from torch import Tensor, nn

from .attention_pooling import WIDTH, AttentionProbe
from .text_encoder import pooled_text


class TokenReadout(nn.Module):
    """Image tokens and instruction to a normalised environment state [B, S].

    Args:
        cameras: C.
        grid: (rows, cols) of each camera's tokens, N = rows * cols, row-major.
        image_dim: Dv.
        text_dim: Dt.
        state_dim: S.
        heads: attention poolings side by side.
    """

    def __init__(self, cameras: int, grid: tuple[int, int], image_dim: int, text_dim: int, state_dim: int,
                 heads: int = 1) -> None:
        super().__init__()
        self.pool = AttentionProbe(cameras * grid[0] * grid[1], image_dim, lambda: nn.Linear(text_dim, WIDTH),
                                   outputs=state_dim, heads=heads)

    def forward(self, image_tokens: Tensor, text_tokens: Tensor, text_mask: Tensor) -> Tensor:
        return self.pool(image_tokens.flatten(1, 2), pooled_text(text_tokens, text_mask))
