"""What keeps SAC's critic from running off where the replay buffer holds no data.

Why: SAC's actor climbs the critic. Every SAC run on a frozen DUST policy here ended with the critic's Q, at the
actor's own actions, far above any return the sparse reward can pay (1): 1.34 (steering, fixed std), ~2
(residual), ~30 within 1,100 RL steps at 20 updates per step (steering, learnt entropy), and still ~5 and rising
with LayerNorm (docs/results/2026-11-26-steering-headroom-on-stack.md). Each bootstrapped target then carries the
inflated Q of the next state, so the critic fits its own overestimate with a small loss.

:class:`LayerNormReLU` (``dust-rl finetune --layer-norm``) is SB3's ``activation_fn``, instantiated without
arguments after each hidden linear layer. A layer normalised before its ReLU has bounded entries (each at most
sqrt(width)), so the critic's output is bounded by its last layer's weights whatever the action (Ball et al. 2023,
RLPD; DSRL's critics and actors use it too). It slows the climb; it does not stop it. Squashing the critic's output
into the returns the reward can pay (``sac --q-bounds``, retired) held Q at the bound instead and gained nothing;
``--finite-horizon`` (:mod:`dust_rl.rl.frozen_policy_env`) removes the bootstrapping past the time limit that asked
for a Q of 1 everywhere.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class LayerNormReLU(nn.Module):
    """ReLU of the input normalised over its last dimension (no learnt scale or shift)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(F.layer_norm(x, x.shape[-1:]))
