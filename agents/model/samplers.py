"""Euler samplers for DUST: synchronous, asynchronous and action-only.

A sampler is a schedule (a list of :class:`DenoiseStep`) run by
:func:`run_schedule`. Each step evaluates the model once at (tau_a, tau_o) and
moves each modality by its own step size; a step size of 0 leaves that
modality unchanged.

- Asynchronous (DUST): N_o = q * N_A. At global step j = 0..N_o-1 the model
  sees tau_o = j / N_o and tau_a = floor(j / q) * q / N_o; vision moves by
  1 / N_o every step, actions by q / N_o at the last step of each block of q
  (j % q == q - 1). So vision makes N_o updates and actions N_A, and every
  step labels each stream with the noise level its tokens hold: had actions
  moved at a block's first step, the model would be told the old tau_a for
  the q - 1 steps after it. Moving last also lets each action step read the
  vision tokens at their least noisy within the block.
- Synchronous: the asynchronous schedule with q = 1 (both streams share steps).
- Action-only: the vision tokens stay pure noise at tau_o = 0 and actions take
  N_A steps; the only option for the action-only variant.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..config import DustConfig
from .flow_matching import cpu_drawn

if TYPE_CHECKING:  # the model imports this module to sample
    from .dust_model import ChunkContext, DustModel

VisionSource = Callable[["DenoiseStep"], tuple[Tensor, float]]
"""Per step, the vision tokens [B, N_o, Dv] and their flow time tau_o that the model sees instead of the ones
the sampler integrates: the oracle-future test (:mod:`dust_rl.diagnose.world_model`) feeds the true future,
pure noise or another episode's future this way."""


@dataclass(frozen=True)
class DenoiseStep:
    """One model evaluation of a sampler and the Euler moves it triggers.

    Attributes:
        index: global step j.
        tau_a: action flow time fed to the model.
        tau_o: vision flow time fed to the model.
        dt_a: action Euler step (0: actions unchanged).
        dt_o: vision Euler step (0: vision unchanged).
    """

    index: int
    tau_a: float
    tau_o: float
    dt_a: float
    dt_o: float


def async_schedule(n_action_steps: int, vision_step_ratio: int) -> list[DenoiseStep]:
    """DUST's asynchronous schedule with N_o = vision_step_ratio * n_action_steps vision steps."""
    q = vision_step_ratio
    n_o = q * n_action_steps
    return [
        DenoiseStep(j, (j // q) * q / n_o, j / n_o, q / n_o if j % q == q - 1 else 0.0, 1.0 / n_o) for j in range(n_o)
    ]


def sync_schedule(n_steps: int) -> list[DenoiseStep]:
    """Both modalities share the same n_steps steps."""
    return async_schedule(n_steps, 1)


def action_only_schedule(n_steps: int) -> list[DenoiseStep]:
    """Denoise actions only; the vision input stays noise at tau_o = 0."""
    return [DenoiseStep(j, j / n_steps, 0.0, 1.0 / n_steps, 0.0) for j in range(n_steps)]


def schedule_for(config: DustConfig) -> list[DenoiseStep]:
    """The schedule a config asks for."""
    name = config.sampler_name
    if name == "async":
        return async_schedule(config.n_action_steps, config.vision_step_ratio)
    if name == "sync":
        return sync_schedule(config.n_action_steps)
    return action_only_schedule(config.n_action_steps)


def _given(name: str, noise: Tensor, like: Tensor, layout: str) -> Tensor:
    """A given initial noise as ``like``'s dtype and device; ValueError unless it has ``like``'s shape."""
    if noise.shape != like.shape:
        raise ValueError(f"{name} must have shape {tuple(like.shape)} {layout}, got {tuple(noise.shape)}")
    return noise.to(like)


@torch.no_grad()
def run_schedule(
    model: DustModel,
    ctx: ChunkContext,
    schedule: list[DenoiseStep],
    generator: torch.Generator | None = None,
    callback: Callable[[DenoiseStep, Tensor, Tensor | None], None] | None = None,
    action_noise: Tensor | None = None,
    noise_scale: float = 1.0,
    vision_source: VisionSource | None = None,
    vision_noise: Tensor | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Integrate both modalities from noise along ``schedule``.

    Args:
        model: the velocity network.
        ctx: chunk context from :meth:`DustModel.encode_context` (computed once per chunk).
        schedule: steps from one of the schedule functions.
        generator: random source of the initial noise (actions first, then vision).
        callback: called after every step with (step, actions, vision) as they now stand,
            e.g. to count or inspect updates.
        action_noise: [B, H, Da], the initial action noise to start from instead of the drawn one (the
            sampler is deterministic given it and the vision noise: an RL actor can steer a frozen policy
            through it). The action noise is drawn and discarded all the same (unless ``vision_noise`` is
            given too), so the vision noise does not change.
        noise_scale: factor on the drawn action noise (:attr:`..config.SamplerConfig.noise_scale`); not
            applied to a given ``action_noise``.
        vision_source: the vision tokens and tau_o each step feeds the model instead of the integrated ones
            (the vision noise is drawn all the same, so the action noise does not change with it).
        vision_noise: [B, N_o, Dv], the initial vision noise to start from instead of the drawn one. With
            ``action_noise`` too, nothing is drawn and the chunk is a deterministic function of the two (noise
            steering's steps, :mod:`dust_rl.rl.steering`); alone, the action noise is drawn as before.

    Returns:
        (action chunk [B, H, Da], future-vision tokens [B, N_o, Dv] or None: the last step's, given or
        integrated).
    """
    cfg = model.config
    b, device = ctx.batch_size, ctx.state_token.device
    if action_noise is None or vision_noise is None:  # drawn first, so the vision noise drawn after stays as it was
        action = cpu_drawn(torch.randn, b, cfg.horizon, cfg.action_dim, generator=generator, device=device)
    else:
        action = torch.empty(b, cfg.horizon, cfg.action_dim, device=device)
    if action_noise is not None:
        action = _given("action_noise", action_noise, action, "[B, H, Da]")
    else:
        action = action * noise_scale
    vision = None
    if cfg.has_vision:
        if vision_noise is None:
            vision = cpu_drawn(torch.randn, b, cfg.n_vision_tokens, cfg.vision_dim, generator=generator,
                               device=device)
        else:
            vision = _given("vision_noise", vision_noise,
                            torch.empty(b, cfg.n_vision_tokens, cfg.vision_dim, device=device), "[B, N_o, Dv]")
    for step in schedule:
        tau_a = torch.full((b,), step.tau_a, device=device)
        tau_o_value = step.tau_o
        if vision is not None and vision_source is not None:
            vision, tau_o_value = vision_source(step)
        tau_o = None if vision is None else torch.full((b,), tau_o_value, device=device)
        need_action = step.dt_a != 0
        need_vision = step.dt_o != 0 and vision is not None and vision_source is None
        if need_action or need_vision:  # a vision-only step of a given future moves nothing
            v_a, v_o = model(ctx, action, vision, tau_a, tau_o, need_action, need_vision)
        if need_action:
            action = torch.add(action, v_a, alpha=step.dt_a)
        if need_vision:
            vision = torch.add(vision, v_o, alpha=step.dt_o)
        if callback is not None:
            callback(step, action, vision)
    return action, vision
