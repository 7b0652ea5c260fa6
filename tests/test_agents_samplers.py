"""Samplers: schedules, update counts, determinism."""

from __future__ import annotations

import math

import pytest
import torch

from dust_rl.agents import (
    DustConfig,
    DustModel,
    SamplerConfig,
    action_only_schedule,
    async_schedule,
    random_batch,
    run_schedule,
    schedule_for,
    sync_schedule,
)

pytestmark = pytest.mark.usefixtures("one_thread")


def tiny(**overrides) -> DustConfig:
    sizes = dict(action_dim=3, horizon=6, state_dim=5, vision_dim=7, vision_grid=(2, 3), cond_dim=11, d_model=32,
                 n_heads=4, n_mmdit=2, n_dit=2)
    return DustConfig(**{**sizes, **overrides})


def trained_like_agent(config: DustConfig) -> DustModel:
    """An agent whose zero-initialised output layers are randomised, so every step moves its stream."""
    agent = DustModel(config).eval()
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in agent.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
    return agent


def obs_for(config: DustConfig, batch_size: int = 2):
    return random_batch(config, batch_size, n_cond_tokens=4, generator=torch.Generator().manual_seed(1)).select(
        "state", "cond_tokens"
    )


@pytest.mark.parametrize("n_action_steps,q", [(4, 1), (4, 4), (2, 8), (3, 2)])
def test_async_schedule_matches_the_paper(n_action_steps, q):
    steps = async_schedule(n_action_steps, q)
    n_o = q * n_action_steps
    assert len(steps) == n_o
    for j, step in enumerate(steps):
        assert step.tau_o == pytest.approx(j / n_o)
        assert step.tau_a == pytest.approx((j // q) * q / n_o)
        assert step.dt_o == pytest.approx(1 / n_o)
        assert step.dt_a == (pytest.approx(q / n_o) if j % q == q - 1 else 0.0)
    assert sum(s.dt_a for s in steps) == pytest.approx(1.0)
    assert sum(s.dt_o for s in steps) == pytest.approx(1.0)


@pytest.mark.parametrize("schedule", [async_schedule(4, 1), async_schedule(4, 4), async_schedule(2, 8),
                                      async_schedule(3, 2), action_only_schedule(4)],
                         ids=["q1", "q4", "q8", "q2", "action_only"])
def test_every_step_labels_each_stream_with_its_noise_level(schedule):
    level_a = level_o = 0.0  # tau of the tokens: 0 is the initial noise, 1 the data
    tolerance = 4 * len(schedule) * torch.finfo(torch.float64).eps
    for step in schedule:
        assert math.isclose(step.tau_a, level_a, abs_tol=tolerance), step
        assert math.isclose(step.tau_o, level_o, abs_tol=tolerance), step
        level_a, level_o = level_a + step.dt_a, level_o + step.dt_o
    assert math.isclose(level_a, 1.0, abs_tol=tolerance)
    assert math.isclose(level_o, 0.0 if schedule[0].dt_o == 0 else 1.0, abs_tol=tolerance)


def test_sync_and_action_only_schedules():
    assert sync_schedule(5) == async_schedule(5, 1)
    steps = action_only_schedule(4)
    assert [s.tau_a for s in steps] == [0.0, 0.25, 0.5, 0.75]
    assert all(s.tau_o == 0.0 and s.dt_o == 0.0 for s in steps)


@pytest.mark.parametrize("n_action_steps,q", [(4, 1), (4, 4), (2, 8)])
def test_async_sampler_makes_n_o_vision_and_n_a_action_updates(n_action_steps, q):
    config = tiny(vision_step_ratio=q, n_action_steps=n_action_steps)
    agent = trained_like_agent(config)
    states = []
    agent.predict_action(obs_for(config), schedule_for(config), torch.Generator().manual_seed(0),
                         lambda step, a, o: states.append((a, o)))
    assert len(states) == q * n_action_steps
    g = torch.Generator().manual_seed(0)  # the initial noise, drawn as the sampler draws it (actions first)
    previous_a = torch.randn(2, config.horizon, config.action_dim, generator=g)
    previous_o = torch.randn(2, config.n_vision_tokens, config.vision_dim, generator=g)
    moved_a, moved_o = [], []
    for a, o in states:
        moved_a.append(not torch.equal(a, previous_a))
        moved_o.append(not torch.equal(o, previous_o))
        previous_a, previous_o = a, o
    assert moved_a == [j % q == q - 1 for j in range(q * n_action_steps)]  # actions move last in each block
    assert all(moved_o)


def test_action_only_sampling_leaves_vision_as_noise():
    config = tiny(sampler="action_only")
    agent = trained_like_agent(config)
    states = []
    agent.predict_action(obs_for(config), schedule_for(config), torch.Generator().manual_seed(0),
                         lambda step, a, o: states.append((a, o)))
    g = torch.Generator().manual_seed(0)
    torch.randn(2, config.horizon, config.action_dim, generator=g)  # the sampler draws action noise first
    initial_vision = torch.randn(2, config.n_vision_tokens, config.vision_dim, generator=g)
    assert len(states) == config.n_action_steps
    assert all(torch.equal(o, initial_vision) for _, o in states)
    assert all(not torch.equal(a, b) for (a, _), (b, _) in zip(states, states[1:]))


@pytest.mark.parametrize("config", [tiny(vision_step_ratio=4), tiny(variant="joint"), tiny(variant="action_only")],
                         ids=["dust-async", "joint-sync", "action_only"])
def test_seeded_sampling_is_bitwise_deterministic(config):
    agent = trained_like_agent(config)
    obs = obs_for(config)
    first = agent.predict_action(obs, schedule_for(config), torch.Generator().manual_seed(7))
    second = agent.predict_action(obs, schedule_for(config), torch.Generator().manual_seed(7))
    other = agent.predict_action(obs, schedule_for(config), torch.Generator().manual_seed(8))
    for key in first.keys():
        assert torch.equal(first[key], second[key])
        assert not torch.equal(first[key], other[key])


def test_schedule_can_be_overridden_at_test_time():
    config = tiny()  # trained for N_A = N_o = 4
    agent = trained_like_agent(config)
    seen = []
    agent.predict_action(obs_for(config), async_schedule(4, 8), callback=lambda s, a, o: seen.append(s))
    assert len(seen) == 32 and sum(s.dt_a > 0 for s in seen) == 4


def test_run_schedule_returns_final_state_of_callback():
    config = tiny()
    agent = trained_like_agent(config)
    obs = obs_for(config)
    ctx = agent.encode_context(obs["state"], obs["cond_tokens"])
    seen = []
    action, vision = run_schedule(agent, ctx, async_schedule(2, 2), torch.Generator().manual_seed(0),
                                  lambda s, a, o: seen.append((a, o)))
    assert torch.equal(action, seen[-1][0]) and torch.equal(vision, seen[-1][1])


def test_noise_scale_scales_the_drawn_action_noise_only():
    config = tiny()
    agent = trained_like_agent(config)
    obs = obs_for(config)
    ctx = agent.encode_context(obs["state"], obs["cond_tokens"])

    def sample(seed: int, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
        return run_schedule(agent, ctx, async_schedule(2, 2), torch.Generator().manual_seed(seed), **kwargs)

    drawn = torch.randn(obs["state"].shape[0], config.horizon, config.action_dim,
                        generator=torch.Generator().manual_seed(0))  # the schedule's first draw
    half, half_given = sample(0, noise_scale=0.5), sample(0, action_noise=0.5 * drawn)
    assert torch.equal(half[0], half_given[0]) and torch.equal(half[1], half_given[1])
    assert torch.equal(sample(0, action_noise=drawn, noise_scale=0.0)[0], sample(0)[0])  # given noise: unscaled
    assert torch.equal(sample(0, noise_scale=1.0)[0], sample(0)[0])
    assert not torch.equal(sample(0)[0], sample(1)[0])


def test_noise_scale_zero_makes_an_action_only_policy_deterministic():
    config = tiny(variant="action_only")
    agent = trained_like_agent(config)
    obs = obs_for(config)
    ctx = agent.encode_context(obs["state"], obs["cond_tokens"])
    chunks = [run_schedule(agent, ctx, action_only_schedule(2), torch.Generator().manual_seed(seed),
                           noise_scale=scale)[0] for scale in (0.0, 1.0) for seed in (0, 1)]
    assert torch.equal(chunks[0], chunks[1]) and not torch.equal(chunks[2], chunks[3])


@pytest.mark.parametrize("scale", [-0.1, float("nan"), float("inf")])
def test_sampler_config_rejects_a_bad_noise_scale(scale):
    with pytest.raises(ValueError, match="noise_scale"):
        SamplerConfig(noise_scale=scale)
