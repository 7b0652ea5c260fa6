"""Exponential moving average of a module's weights, for evaluation and the saved policy.

Flow-matching policies sampled from averaged weights are smoother and more
reliable than from the last optimiser step (diffusion_policy, GR00T). The
average lives in a TensorDict beside the module and is swapped in only while
it is used, so the optimiser never sees it.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDict
from torch import nn


class EMA:
    """Averaged copy of ``module``'s floating-point parameters and buffers.

    The decay ramps up as ``min(decay, (1 + n) / (10 + n))`` after ``n`` updates, so early
    averages are not dominated by the random initialisation.

    Args:
        module: the trained module (its live weights are read at each update).
        decay: the final decay per update.
    """

    def __init__(self, module: nn.Module, decay: float = 0.999) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.module, self.decay, self.updates = module, decay, 0
        live = TensorDict.from_module(module)
        self.live = live.select(*[k for k, v in live.items(True, True) if v.is_floating_point()])
        self.average = self.live.detach().clone()

    @torch.no_grad()
    def update(self) -> None:
        """Move the average towards the module's current weights."""
        self.updates += 1
        decay = min(self.decay, (1 + self.updates) / (10 + self.updates))
        self.average.lerp_(self.live.detach(), 1.0 - decay)

    def applied(self):
        """Context manager: the module holds the averaged weights inside it, its own weights after."""
        return self.average.to_module(self.module)

    def state_dict(self) -> dict:
        return {"average": self.average.flatten_keys(".").to_dict(), "updates": self.updates}

    def load_state_dict(self, state: Mapping) -> None:
        average = TensorDict(dict(state["average"])).unflatten_keys(".")
        if set(average.keys(True, True)) != set(self.average.keys(True, True)):
            raise ValueError("EMA state does not match the module's parameters")
        self.average.update_(average)
        self.updates = int(state["updates"])
