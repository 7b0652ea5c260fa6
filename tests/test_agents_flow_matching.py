"""Flow-matching pieces: tau sampling, interpolation, masked losses."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import rounding_tolerance

from dust_rl.agents import action_validity, decoupled_loss, interpolate, masked_mse, sample_tau, velocity_target

pytestmark = pytest.mark.usefixtures("one_thread")


def test_tau_follows_shifted_beta():
    tau = sample_tau(200_000, s=0.999, alpha=1.5, generator=torch.Generator().manual_seed(0))
    assert tau.min() >= 0 and tau.max() <= 1
    # Tolerances: ~5 standard errors of a mean of 200k draws (sd(tau) ~ 0.26; a proportion's sd <= 0.5).
    # u ~ Beta(1.5, 1): E[u] = 0.6, so E[tau] = (0.999 - 0.6) / 0.999 (clamping moves it by < 1e-5).
    assert tau.mean().item() == pytest.approx((0.999 - 0.6) / 0.999, abs=3e-3)
    # P(tau <= x) = P(u >= s(1-x)) = 1 - (s(1-x))**1.5 ; favours noisy inputs.
    for x in (0.1, 0.5, 0.9):
        expected = 1 - (0.999 * (1 - x)) ** 1.5
        assert (tau <= x).float().mean().item() == pytest.approx(expected, abs=5e-3)
    # u > s would give tau < 0: those draws are clamped to pure noise.
    clamped = sample_tau(200_000, s=0.8, alpha=1.5, generator=torch.Generator().manual_seed(1))
    assert (clamped == 0).float().mean().item() == pytest.approx(1 - 0.8**1.5, abs=5e-3)


def test_tau_is_seeded():
    a = sample_tau(64, generator=torch.Generator().manual_seed(3))
    b = sample_tau(64, generator=torch.Generator().manual_seed(3))
    c = sample_tau(64, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_interpolation_endpoints_and_velocity():
    g = torch.Generator().manual_seed(0)
    x, eps = torch.randn(3, 5, 2, generator=g), torch.randn(3, 5, 2, generator=g)
    tau = torch.tensor([0.0, 0.25, 1.0])
    xt = interpolate(x, eps, tau)
    torch.testing.assert_close(xt[0], eps[0])
    torch.testing.assert_close(xt[1], 0.25 * x[1] + 0.75 * eps[1])
    torch.testing.assert_close(xt[2], x[2])
    # The path is straight: a finite difference in tau gives the target velocity. Divided by the step taken
    # in float32 (hi - lo is exact); each endpoint (two terms) carries rounding, which the quotient scales by 1/h.
    h = 1e-2
    lo = tau.clamp(max=1 - h)
    hi = lo + h
    fd = (interpolate(x, eps, hi) - interpolate(x, eps, lo)) / (hi - lo).view(-1, 1, 1)
    scale = max(x.abs().max().item(), eps.abs().max().item())
    torch.testing.assert_close(fd, velocity_target(x, eps), rtol=0,
                               atol=rounding_tolerance(x.dtype, n_terms=2, depth=2, scale=scale) / h)


def test_masked_mse_ignores_invalid_entries_even_nan():
    pred = torch.zeros(2, 3, 4, requires_grad=True)
    target = torch.ones(2, 3, 4)
    target[1] = math.nan
    valid = torch.tensor([[True, True, False], [False, False, False]])
    loss = masked_mse(pred, target, valid)
    loss.backward()
    assert loss.item() == pytest.approx(1.0)
    assert torch.isfinite(pred.grad).all()
    assert (pred.grad[0, :2] != 0).all() and (pred.grad[0, 2] == 0).all() and (pred.grad[1] == 0).all()
    assert masked_mse(pred, target, torch.zeros(2, 3, dtype=torch.bool)).item() == 0.0


def test_action_validity_combines_padding_and_action_free():
    has_action = torch.tensor([True, False])
    is_pad = torch.tensor([[False, True], [False, False]])
    valid = action_validity(2, 2, has_action, is_pad)
    assert valid.tolist() == [[True, False], [False, False]]
    assert action_validity(2, 2, None, None).all()


def test_decoupled_loss_weights_the_vision_term():
    va, ta = torch.zeros(2, 3, 1), torch.ones(2, 3, 1)
    vo, to = torch.zeros(2, 4, 5), 2 * torch.ones(2, 4, 5)
    valid = torch.ones(2, 3, dtype=torch.bool)
    out = decoupled_loss(va, ta, valid, vo, to, lambda_wm=0.5)
    assert out["loss_action"].item() == pytest.approx(1.0)
    assert out["loss_vision"].item() == pytest.approx(4.0)
    assert out["loss"].item() == pytest.approx(3.0)
    assert decoupled_loss(va, ta, valid, None, None, 1.0)["loss"].item() == pytest.approx(1.0)


def test_the_vision_loss_is_a_mean_per_element_at_any_grid():
    """lambda_wm weighs a 4x4 target as much as a 2x2 one (a mean over samples only would grow with the tokens)."""
    va, ta, valid = torch.zeros(3, 2, 1), torch.zeros(3, 2, 1), torch.ones(3, 2, dtype=torch.bool)
    for tokens in (4, 16):
        vo, to = torch.zeros(3, tokens, 5), 2 * torch.ones(3, tokens, 5)
        assert decoupled_loss(va, ta, valid, vo, to, lambda_wm=1.0)["loss_vision"].item() == pytest.approx(4.0)
