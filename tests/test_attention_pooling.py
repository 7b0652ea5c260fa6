"""The diagnostic attention probe learns what only the condition can point at."""

from __future__ import annotations

import torch
from torch import nn

from dust_rl.agents.heads.attention_pooling import WIDTH, AttentionProbe, standardise

TOKENS, DIM, SAMPLES = 6, 4, 512


def _fit(early: bool) -> float:
    """Mean squared error, after fitting, of "the first feature of the token the condition names"."""
    torch.manual_seed(0)
    x = torch.randn(SAMPLES, TOKENS, DIM)
    named = torch.randint(0, TOKENS, (SAMPLES,))
    target = x[torch.arange(SAMPLES), named, :1]
    probe = AttentionProbe(TOKENS, DIM, lambda: nn.Embedding(TOKENS, WIDTH), outputs=1, early=early)
    optimizer = torch.optim.Adam(probe.parameters(), lr=3e-3)
    for _ in range(400):
        loss = (probe(x, named) - target).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        return (probe(x, named) - target).square().mean().item()


def test_probe_reads_the_token_the_condition_names():
    variance = 1.0  # of the standard-normal target: what predicting its mean scores
    assert _fit(early=True) < 0.2 * variance


def test_standardise_uses_the_training_statistics_for_every_set():
    train, other = torch.randn(50, 3, 2) * 4 + 1, torch.randn(10, 3, 2)
    scaled_train, scaled_other = standardise(train, other)
    torch.testing.assert_close(scaled_train.mean((0, 1)), torch.zeros(2), atol=1e-5, rtol=0)
    mean, std = train.mean((0, 1)), train.std((0, 1)) + 1e-5
    torch.testing.assert_close(scaled_other, (other - mean) / std)
