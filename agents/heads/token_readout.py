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
instruction (its tokens' mean) added to each token before the attention, so
which object is named decides where it looks. With ``readout_text="attention"``
each head also reads the instruction through its own learnt attention over
its tokens, and the result is that head's query: the mean of "stack the red
cube on the blue cube" is nearly that of "stack the blue cube on the red
cube", while a head can pick out the first colour and another the second. With
``proprio_dim`` the robot state joins the instruction in that condition and is read again by the final MLP:
the wrist camera moves with the hand, so where it sees an object says where the object is only given where the
hand is.

==============  ==================  =====================================
tensor          shape               meaning
==============  ==================  =====================================
image_tokens    [B, C, N, Dv]       standardised condition tokens per camera
text_tokens     [B, L, Dt]          instruction tokens (mask [B, L])
state           [B, P]              normalised robot state (``proprio_dim`` P > 0 only)
estimate        [B, S]              normalised environment state
==============  ==================  =====================================
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..encoders.text_encoder import pooled_text
from .attention_pooling import WIDTH, AttentionProbe


class TokenReadout(nn.Module):
    """Image tokens, instruction (and robot state) to a normalised environment state [B, S].

    Args:
        cameras: C.
        grid: (rows, cols) of each camera's tokens, N = rows * cols, row-major.
        image_dim: Dv.
        text_dim: Dt.
        state_dim: S.
        heads: attention poolings side by side.
        proprio_dim: P, the robot state's size; 0: the read-out does not read it.
        text_attention: give each head a query read from the instruction by its own attention over the tokens.
    """

    def __init__(self, cameras: int, grid: tuple[int, int], image_dim: int, text_dim: int, state_dim: int,
                 heads: int = 1, proprio_dim: int = 0, text_attention: bool = False) -> None:
        super().__init__()
        self.proprio_dim = proprio_dim
        self.pool = AttentionProbe(cameras * grid[0] * grid[1], image_dim,
                                   lambda: nn.Linear(text_dim + proprio_dim, WIDTH), outputs=state_dim, heads=heads,
                                   condition_at_head=proprio_dim > 0)
        # Per head, an attention over the instruction's tokens and the query its result makes.
        self.text_attend = nn.Linear(text_dim, heads) if text_attention else None
        self.text_query = nn.Linear(text_dim, WIDTH) if text_attention else None

    def forward(self, image_tokens: Tensor, text_tokens: Tensor, text_mask: Tensor,
                state: Tensor | None = None) -> Tensor:
        text = pooled_text(text_tokens, text_mask)
        condition = torch.cat([text, state], -1) if self.proprio_dim else text
        queries = None
        if self.text_attend is not None:  # a masked softmax over the instruction's tokens per head
            logits = self.text_attend(text_tokens).masked_fill(~text_mask[..., None], float("-inf"))  # [B, L, heads]
            queries = self.text_query(torch.einsum("blk,bld->bkd", logits.softmax(1), text_tokens))
        return self.pool(image_tokens.flatten(1, 2), condition, queries)
