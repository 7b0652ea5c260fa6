"""LayerNorm in the RL agent's MLPs: a critic whose Q cannot run off far from its data.

Why: SAC's actor climbs the critic. Every SAC run on a frozen DUST policy here ended with the critic's Q at
actions the replay buffer never held far above any return the sparse reward can pay (1): 1.34 (steering,
fixed std), ~2 (residual), and ~30 within 1,100 RL steps at 20 updates per step (steering, learnt entropy;
BENCHMARKS "Headroom for noise steering on stack"). A layer normalised before its ReLU has a bounded output
(each entry at most sqrt(width)), so the critic's output is bounded by its last layer's weights whatever the
action: the extrapolation that the actor exploits is capped (Ball et al. 2023, RLPD; DSRL's critics and actors
use it too). :class:`LayerNormReLU` goes in as SB3's ``activation_fn``: SB3 instantiates it, without
arguments, after each hidden linear layer.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class LayerNormReLU(nn.Module):
    """ReLU of the input normalised over its last dimension (no learnt scale or shift)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(F.layer_norm(x, x.shape[-1:]))
