"""The optimiser's companions, from torch: the warm-up cosine learning rate and the weight average.

Flow-matching policies sampled from averaged weights are smoother and more
reliable than from the last optimiser step (diffusion_policy, GR00T), so
evaluation and the saved policy use an exponential moving average of the
trained weights (``torch.optim.swa_utils.AveragedModel``). Its decay ramps up
as ``min(decay, (1 + n) / (10 + n))`` after ``n`` averaged steps, so a short
run's average is not dominated by the random initialisation.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch
from tensordict import TensorDict
from torch import Tensor, nn
from torch.optim.lr_scheduler import CosineAnnealingLR, LinearLR, LRScheduler, SequentialLR
from torch.optim.swa_utils import AveragedModel


def warmup_cosine(optimizer: torch.optim.Optimizer, total_steps: int, warmup_fraction: float) -> LRScheduler:
    """Linear warm-up over the first ``warmup_fraction`` of the steps (to the base rate at its last step),
    then cosine to 0 at ``total_steps``; step it once per optimiser step."""
    warmup = min(max(1, round(warmup_fraction * total_steps)), total_steps)
    ramp = LinearLR(optimizer, start_factor=1.0 / warmup, end_factor=1.0, total_iters=max(1, warmup - 1))
    decay = CosineAnnealingLR(optimizer, T_max=max(1, total_steps - warmup))
    return SequentialLR(optimizer, [ramp, decay], milestones=[warmup])


def adamw(parameters: list[nn.Parameter], lr: float, **settings: object) -> torch.optim.AdamW:
    """AdamW, its fused kernel where the parameters' device has one (CPU, CUDA): one pass over every tensor
    instead of a loop of small ops, 13 -> 2.4 ms a step for the 4M-parameter trunk on a 2-core CPU."""
    fused = all(p.device.type in ("cpu", "cuda") for p in parameters) or None
    return torch.optim.AdamW(parameters, lr=lr, fused=fused, **settings)


def weight_average(module: nn.Module, decay: float) -> AveragedModel:
    """An exponential moving average of ``module``'s parameters, starting at their current values.

    Call ``update_parameters(module)`` after each optimiser step; :func:`averaged_weights` swaps it in.
    """
    if not 0.0 <= decay < 1.0:
        raise ValueError(f"EMA decay must be in [0, 1), got {decay}")

    def average(averaged: list[Tensor], current: list[Tensor], count: Tensor) -> None:  # every tensor at once
        torch._foreach_lerp_(averaged, current, 1.0 - min(decay, (1.0 + count.item()) / (10.0 + count.item())))

    ema = AveragedModel(module, multi_avg_fn=average)
    ema.update_parameters(module)  # the first update copies: the average starts at the live weights
    return ema


def averaged_weights(ema: AveragedModel, module: nn.Module) -> AbstractContextManager:
    """Context manager: ``module`` holds ``ema``'s averaged weights inside it, its own weights after."""
    return TensorDict.from_module(ema.module).to_module(module)
