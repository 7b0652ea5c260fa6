"""Training: the loss falls for every variant, and DUST overfits a tiny dataset."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from dust_rl.agents import VARIANTS, DustConfig, DustModel, schedule_for

pytestmark = pytest.mark.usefixtures("one_thread")


def small(variant: str) -> DustConfig:
    return DustConfig(
        variant=variant, action_dim=2, horizon=8, state_dim=4, vision_dim=8, vision_grid=(2, 2), cond_dim=16,
        d_model=64, n_heads=4, n_mmdit=2, n_dit=2,
    )


def toy_dataset(config: DustConfig, size: int, seed: int = 0) -> TensorDict:
    """Distinct conditions, each with its own smooth action chunk (sines of random phase and frequency)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, config.horizon)[None, :, None]
    phase = 2 * math.pi * torch.rand(size, 1, config.action_dim, generator=g)
    freq = 1 + 2 * torch.rand(size, 1, config.action_dim, generator=g)
    return TensorDict(
        {
            "cond_tokens": torch.randn(size, 4, config.cond_dim, generator=g),
            "state": torch.randn(size, config.state_dim, generator=g),
            "action_chunk": torch.sin(2 * math.pi * freq * t + phase),
            "future_tokens": torch.randn(size, config.n_vision_tokens, config.vision_dim, generator=g),
        },
        batch_size=[size],
    )


def train(agent: DustModel, batch: TensorDict, steps: int, lr: float, seed: int = 0) -> None:
    optimizer = torch.optim.AdamW(agent.parameters(), lr=lr, weight_decay=0.0)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        loss = agent.compute_loss(batch, g)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


@pytest.mark.parametrize("variant", VARIANTS)
def test_loss_falls(variant):
    torch.manual_seed(0)
    config = small(variant)
    agent = DustModel(config)
    batch = torch.cat([toy_dataset(config, 4)] * 2)

    def fixed_draw_loss() -> float:
        with torch.no_grad():
            return agent.compute_loss(batch, torch.Generator().manual_seed(123))["loss"].item()

    before = fixed_draw_loss()
    train(agent, batch, steps=60, lr=3e-3)
    assert fixed_draw_loss() < 0.7 * before


def test_dust_overfits_a_tiny_dataset():
    torch.manual_seed(0)
    config = small("dust")
    agent = DustModel(config)
    data = toy_dataset(config, 4)
    obs = data.select("state", "cond_tokens")

    def errors() -> tuple[torch.Tensor, torch.Tensor]:
        out = agent.eval().predict_action(obs, schedule_for(config), torch.Generator().manual_seed(1))
        agent.train()
        return (out["action_chunk"] - data["action_chunk"]).abs(), (out["future_tokens"] - data["future_tokens"]).abs()

    untrained_action, _ = errors()
    assert untrained_action.mean() > 0.4
    train(agent, torch.cat([data] * 8), steps=300, lr=3e-3)
    action_err, vision_err = errors()
    # Worst entry over 8 init x 3 noise seeds and 3 CPU kernel levels: 0.09-0.33; an unlearned chunk is off by ~1.
    assert action_err.mean() < 0.1 and action_err.max() < 0.5, (action_err.mean(), action_err.max())
    assert vision_err.mean() < 0.15, vision_err.mean()
