"""Rectified-flow pieces of DUST: timestep sampling, interpolation, masked losses.

Convention (GR00T, DUST): tau = 0 is pure noise, tau = 1 is data,
x_tau = tau * x + (1 - tau) * eps, and the model regresses the constant
velocity x - eps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Shard:
    """This process's part of a batch split evenly over `count` data-parallel processes (rows
    `index * b .. (index + 1) * b` of `count * b`).

    Why: each process draws the noise of the whole batch from the same generator state and keeps its rows,
    so every sample gets the noise it would get in one process, and all processes' generators stay equal.
    """

    index: int = 0
    count: int = 1

    def __post_init__(self) -> None:
        if not 0 <= self.index < self.count:
            raise ValueError(f"shard {self.index} of {self.count}: need 0 <= index < count")

    def rows(self, total: int) -> slice:
        """This shard's rows of a batch of ``total`` (a multiple of ``count``)."""
        if total % self.count:
            raise ValueError(f"a batch of {total} does not split evenly over {self.count} processes")
        size = total // self.count
        return slice(self.index * size, (self.index + 1) * size)


WHOLE_BATCH = Shard()  # one process: the batch is all there is


def cpu_drawn(draw: Callable[..., Tensor], *shape: int, generator: torch.Generator | None = None,
              device: torch.device | str | None = None, shard: Shard = WHOLE_BATCH) -> Tensor:
    """``draw`` (``torch.randn``, ``torch.rand``) on the CPU, from ``generator`` or torch's global CPU
    generator, then moved to ``device``: a seed gives the same noise, hence the same samples, on any device
    (a CUDA generator draws other numbers), and a CPU generator serves a policy on any device. With a
    ``shard``, ``shape[0]`` is the shard's rows: the whole batch is drawn and the shard's rows kept."""
    whole = draw((shape[0] * shard.count, *shape[1:]), generator=generator)
    return whole[shard.rows(len(whole))].to(device)


def sample_tau(
    batch_size: int,
    *,
    s: float = 0.999,
    alpha: float = 1.5,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    shard: Shard = WHOLE_BATCH,
) -> Tensor:
    """Draw flow times tau = (s - u) / s with u ~ Beta(alpha, 1), clamped to [0, 1].

    Beta(alpha, 1) has CDF u**alpha, so u = U**(1/alpha) with U uniform samples it
    exactly and lets a ``torch.Generator`` seed it (torch's Beta cannot). The
    density favours small tau, i.e. noisy inputs, as in GR00T.

    Args:
        batch_size: number of times to draw.
        s: GR00T's cut-off; u > s would give tau < 0 and is clamped to 0.
        alpha: first Beta parameter.
        generator: random source for reproducibility.
        device: device of the result.
        shard: draw for the whole batch, keep this shard's ``batch_size`` times (:class:`Shard`).

    Returns:
        Float tensor [batch_size] in [0, 1].
    """
    u = cpu_drawn(torch.rand, batch_size, generator=generator, device=device, shard=shard).pow(1.0 / alpha)
    return ((s - u) / s).clamp_(0.0, 1.0)


def interpolate(x: Tensor, eps: Tensor, tau: Tensor) -> Tensor:
    """Point on the straight path from noise ``eps`` (tau=0) to data ``x`` (tau=1).

    Args:
        x: clean data [B, ...].
        eps: noise of the same shape.
        tau: per-sample times [B].
    """
    t = tau.view(-1, *([1] * (x.dim() - 1)))
    return torch.lerp(eps, x, t)


def velocity_target(x: Tensor, eps: Tensor) -> Tensor:
    """Velocity of the straight path, d x_tau / d tau = x - eps."""
    return x - eps


def masked_mse(pred: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
    """Mean squared error over the valid positions only.

    Invalid positions are removed with ``torch.where`` before squaring (not
    multiplied by 0), so they contribute exactly zero gradient even when the
    target holds NaN placeholders. The mean is over valid elements; with none valid the loss is 0.

    Args:
        pred: [B, N, D] prediction.
        target: [B, N, D] target.
        valid: bool [B, N] or [B, 1]; None means all valid.
    """
    if valid is None:
        return (pred - target).square().mean()
    mask = valid.unsqueeze(-1).expand(*pred.shape[:-1], 1)  # a [B, 1] mask covers all N rows of a sample
    # Mask the difference, not the square: d(square)/dx = 2x would turn a masked NaN into a NaN gradient.
    diff = torch.where(mask, pred - target, 0.0)
    return diff.square().sum() / (mask.sum() * pred.shape[-1]).clamp_min(1)


def action_validity(
    batch_size: int,
    horizon: int,
    has_action: Tensor | None,
    action_is_pad: Tensor | None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Bool [B, H] marking the action entries that enter the action loss.

    Args:
        batch_size: B.
        horizon: H.
        has_action: bool [B]; False for action-free (video-only) samples.
        action_is_pad: bool [B, H]; True for entries padded past the episode end.
        device: device of the result.
    """
    valid = torch.ones(batch_size, horizon, dtype=torch.bool, device=device)
    if has_action is not None:
        valid = valid & has_action.view(-1, 1)
    if action_is_pad is not None:
        valid = valid & ~action_is_pad
    return valid


def decoupled_loss(
    v_action: Tensor,
    target_action: Tensor,
    action_valid: Tensor,
    v_vision: Tensor | None,
    target_vision: Tensor | None,
    lambda_wm: float,
) -> dict[str, Tensor]:
    """DUST's loss: L = mse_A + lambda_wm * mse_o.

    Args:
        v_action: predicted action velocity [B, H, Da].
        target_action: A - eps_A [B, H, Da].
        action_valid: bool [B, H] from :func:`action_validity`.
        v_vision: predicted vision velocity [B, N_o, Dv], None without a vision stream.
        target_vision: o - eps_o, None without a vision stream.
        lambda_wm: world-model loss weight.

    Returns:
        Dict with ``loss``, ``loss_action`` and ``loss_vision`` (0 without vision).
    """
    loss_action = masked_mse(v_action, target_action, action_valid)
    if v_vision is None or target_vision is None:
        loss_vision = torch.zeros((), device=v_action.device)
    else:
        loss_vision = masked_mse(v_vision, target_vision)
    return {
        "loss": loss_action + lambda_wm * loss_vision,
        "loss_action": loss_action,
        "loss_vision": loss_vision,
    }
