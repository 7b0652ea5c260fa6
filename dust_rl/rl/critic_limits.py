"""What keeps SAC's critic from running off where the replay buffer holds no data.

Why: SAC's actor climbs the critic. Every SAC run on a frozen DUST policy here ended with the critic's Q, at the
actor's own actions, far above any return the sparse reward can pay (1): 1.34 (steering, fixed std), ~2
(residual), ~30 within 1,100 RL steps at 20 updates per step (steering, learnt entropy), and still ~5 and rising
with LayerNorm (BENCHMARKS "Headroom for noise steering on stack"). Each bootstrapped target then carries the
inflated Q of the next state, so the critic fits its own overestimate with a small loss.

- :class:`LayerNormReLU` (``dust-rl finetune --layer-norm``): SB3's ``activation_fn``, instantiated without
  arguments after each hidden linear layer. A layer normalised before its ReLU has bounded entries (each at most
  sqrt(width)), so the critic's output is bounded by its last layer's weights whatever the action (Ball et al.
  2023, RLPD; DSRL's critics and actors use it too). It slows the climb; it does not stop it.
- :func:`bound_critic` (``--q-bounds LO HI``): the critic's output squashed into [LO, HI], the returns the reward
  can pay (a sparse reward that ends the episode: 0 and 1), so neither the actor nor a bootstrapped target can
  believe in more.
"""

from __future__ import annotations

import torch
from stable_baselines3 import SAC
from torch import nn
from torch.nn import functional as F


class LayerNormReLU(nn.Module):
    """ReLU of the input normalised over its last dimension (no learnt scale or shift)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(F.layer_norm(x, x.shape[-1:]))


class Squash(nn.Module):
    """``low + (high - low) * sigmoid(x)``: any real number into (low, high)."""

    def __init__(self, low: float, high: float) -> None:
        super().__init__()
        if not low < high:
            raise ValueError(f"the Q bounds must satisfy low < high, got ({low}, {high})")
        self.low, self.high = float(low), float(high)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.low + (self.high - self.low) * torch.sigmoid(x)

    def extra_repr(self) -> str:
        return f"low={self.low}, high={self.high}"


def bound_critic(agent: SAC, low: float, high: float) -> None:
    """Squash every Q network of ``agent`` (critic and target alike) into (low, high); adds no parameters, so
    saved state dicts keep their keys."""
    for critic in (agent.critic, agent.critic_target):
        for q_net in critic.q_networks:
            q_net.append(Squash(low, high))
