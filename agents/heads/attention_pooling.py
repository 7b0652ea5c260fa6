"""A small attention-pooling read-out: can frozen tokens give a number a policy needs?

A linear probe of the mean token misses what one object in one place says; a policy's
cross-attention does not. This head is the smallest thing that attends like the policy:
tokens plus an embedded condition (the named colour, the instruction) pass one MLP
residual, a softmax over tokens pools them, and an MLP gives the numbers. Used by
``experiments/frozen_feature_probe.py`` (where the named cube is) and
``experiments/first_move_probe.py`` (the expert's first move), and inside the policy as the
token read-out of the object state (:mod:`.token_readout`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

WIDTH = 64


class AttentionProbe(nn.Module):
    """Tokens [B, N, D] + condition -> ``outputs`` numbers per sample.

    Args:
        tokens: token count ``N`` (each token position has its own learnt embedding).
        dim: token size ``D``.
        condition: builds the module that embeds the condition to ``WIDTH`` (a factory, so the
            parameters are created in a fixed order and a seed gives the same head).
        outputs: size of the prediction.
        early: add the condition to every token before the MLP and the pooling (True), or only to the pooled
            vector (False: the pooling cannot depend on which object is named).
        heads: softmax poolings side by side, their vectors concatenated: one attends to one place, so a
            prediction about several objects needs several.
        condition_at_head: the final MLP also reads the embedded condition beside the pooled vectors (for a
            condition the answer is computed from, such as the pose of the camera that saw the object).
    """

    def __init__(self, tokens: int, dim: int, condition: Callable[[], nn.Module], outputs: int,
                 early: bool = True, heads: int = 1, condition_at_head: bool = False) -> None:
        super().__init__()
        self.early, self.condition_at_head = early, condition_at_head
        self.position = nn.Parameter(0.02 * torch.randn(tokens, WIDTH))
        self.condition = condition()
        self.project = nn.Linear(dim, WIDTH)
        self.mlp = nn.Sequential(nn.Linear(WIDTH, 2 * WIDTH), nn.GELU(), nn.Linear(2 * WIDTH, WIDTH))
        self.attend = nn.Linear(WIDTH, heads)
        self.head = nn.Sequential(nn.Linear((heads + condition_at_head) * WIDTH, 2 * WIDTH), nn.GELU(),
                                  nn.Linear(2 * WIDTH, outputs))

    def forward(self, tokens: Tensor, condition: Tensor, queries: Tensor | None = None) -> Tensor:
        """``queries`` [B, heads, WIDTH]: a query per head, whose dot product with each token joins that head's
        attention logits (the head then looks for what its query names); None: the learnt logits alone."""
        named = self.condition(condition)[:, None]
        h = self.project(tokens) + self.position + (named if self.early else 0)
        h = h + self.mlp(h)
        logits = self.attend(h)  # [B, N, heads]
        if queries is not None:
            logits = logits + torch.einsum("bnw,bkw->bnk", h, queries) / WIDTH ** 0.5
        pooled = torch.einsum("bnk,bnw->bkw", logits.softmax(1), h)  # [B, heads, WIDTH]
        pooled = pooled if self.early else pooled + named
        return self.head(torch.cat([pooled, named], 1).flatten(1) if self.condition_at_head else pooled.flatten(1))


def standardise(train: Tensor, *others: Tensor) -> tuple[Tensor, ...]:
    """Tokens scaled per channel by the training set's mean and spread (all tokens of all samples)."""
    mean, std = train.mean((0, 1)), train.std((0, 1)) + 1e-5
    return tuple((x - mean) / std for x in (train, *others))
