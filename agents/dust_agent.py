"""DUST agent: decoupled flow-matching training and chunk sampling on encoded inputs.

The agent works on already-encoded, already-normalised tensors; the frozen
backbone (vision encoder, text encoder) and the torchrl policy wrapper live
elsewhere. Method names follow diffusion_policy: ``compute_loss(batch)`` and
``predict_action(obs)``.

TensorDict keys (B = batch size):

=====================  ===================  =====================================================
key                    shape / dtype        meaning
=====================  ===================  =====================================================
``cond_tokens``        [B, Nc, Dc] float    backbone condition tokens (image + language)
``cond_mask``          [B, Nc] bool         optional; True where a condition token is valid
``state``              [B, Ds] float        normalised proprioceptive state
``action_chunk``       [B, H, Da] float     normalised action chunk (training; output of predict)
``action_is_pad``      [B, H] bool          optional; True for entries past the episode end
``has_action``         [B] bool             optional; False for action-free (video-only) samples
``future_tokens``      [B, N_o, Dv] float   frozen embedding of the frame after the chunk (t+H);
                                            training target, and predicted by ``predict_action``
``future_is_clamped``  [B] bool             optional; True where t+H lies past the episode's last
                                            stored row, so ``future_tokens`` hold that row instead
=====================  ===================  =====================================================

``action_is_pad`` entries and action-free samples are left out of the action
loss, and clamped futures out of the vision loss: the last stored row is the
observation before the final action, not the frame H steps on, and a padded
chunk's repeated actions are no more real than that frame.

An action-free sample also gets pure-noise action tokens (tau_A = 0 in
the decoupled variants, as UWM does), so the vision stream learns the future
marginalised over actions, and the sampler's first steps (tau_A = 0) see the
same input distribution.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict
from torch import nn

from .config import DustConfig
from .dust_model import DustModel
from .flow_matching import action_validity, decoupled_loss, interpolate, sample_tau, velocity_target
from .samplers import DenoiseStep, run_schedule, schedule_for


class DustAgent(nn.Module):
    """Trainable DUST policy core (or one of its baselines) over encoded inputs.

    Args:
        config: model, loss and sampler settings.
    """

    def __init__(self, config: DustConfig) -> None:
        super().__init__()
        self.config = config
        self.model = DustModel(config)
        self.schedule = schedule_for(config)

    def compute_loss(self, batch: TensorDict, generator: torch.Generator | None = None) -> TensorDict:
        """Decoupled flow-matching loss of one batch.

        Args:
            batch: keys listed in the module docstring (``future_tokens`` unused by action_only).
            generator: random source of tau and noise (tau_A, tau_o, eps_A, eps_o in that order).

        Returns:
            TensorDict with scalar ``loss`` (to minimise), ``loss_action`` and ``loss_vision``.
        """
        cfg = self.config
        action = batch["action_chunk"]
        b, device = action.shape[0], action.device
        has_action = batch.get("has_action", None)
        valid = action_validity(b, cfg.horizon, has_action, batch.get("action_is_pad", None), device)
        ctx = self.model.encode_context(batch["state"], batch["cond_tokens"], batch.get("cond_mask", None))

        tau_a = sample_tau(b, s=cfg.tau_s, alpha=cfg.tau_alpha, generator=generator, device=device)
        tau_o = sample_tau(b, s=cfg.tau_s, alpha=cfg.tau_alpha, generator=generator, device=device)
        if not cfg.decoupled:
            tau_o = tau_a
        eps_a = torch.randn(action.shape, generator=generator, device=device)
        noisy_action = interpolate(action, eps_a, tau_a)
        if has_action is not None:
            # No action to interpolate towards: the action tokens are pure noise.
            noisy_action = torch.where(has_action.view(-1, 1, 1), noisy_action, eps_a)
            if cfg.decoupled:
                tau_a = torch.where(has_action, tau_a, 0.0)

        noisy_vision = target_vision = None
        if cfg.has_vision:
            future = batch["future_tokens"]
            eps_o = torch.randn(future.shape, generator=generator, device=device)
            noisy_vision = interpolate(future, eps_o, tau_o)
            target_vision = velocity_target(future, eps_o)
        v_a, v_o = self.model(ctx, noisy_action, noisy_vision, tau_a, tau_o if cfg.has_vision else None)
        clamped = batch.get("future_is_clamped", None)
        losses = decoupled_loss(v_a, velocity_target(action, eps_a), valid, v_o, target_vision, cfg.lambda_wm,
                                None if clamped is None else ~clamped)
        return TensorDict(losses, batch_size=[])

    @torch.no_grad()
    def predict_action(
        self,
        obs: TensorDict,
        generator: torch.Generator | None = None,
        callback: Callable[[DenoiseStep, torch.Tensor, torch.Tensor | None], None] | None = None,
        schedule: list[DenoiseStep] | None = None,
    ) -> TensorDict:
        """Sample an action chunk (and, with a vision stream, the predicted future tokens).

        Args:
            obs: ``state``, ``cond_tokens`` and optionally ``cond_mask`` and ``action_noise`` [B, H, Da]
                (the initial action noise, :func:`.samplers.run_schedule`).
            generator: random source of the initial noise; same seed, same chunk.
            callback: called after every denoising step (see :func:`.samplers.run_schedule`).
            schedule: overrides the configured sampler, e.g. ``async_schedule(4, 8)`` for
                test-time scaling to N_o = 32 vision steps.

        Returns:
            TensorDict [B] with ``action_chunk`` [B, H, Da] and, unless action_only,
            ``future_tokens`` [B, N_o, Dv].
        """
        ctx = self.model.encode_context(obs["state"], obs["cond_tokens"], obs.get("cond_mask", None))
        steps = self.schedule if schedule is None else schedule
        action, vision = run_schedule(self.model, ctx, steps, generator, callback, obs.get("action_noise", None))
        out = {"action_chunk": action}
        if vision is not None:
            out["future_tokens"] = vision
        return TensorDict(out, batch_size=[ctx.batch_size])
