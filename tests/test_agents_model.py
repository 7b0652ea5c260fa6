"""DUST trunk, its loss and sampling: shapes, per-stream timestep conditioning, masks, caching, loss masking."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_close_up_to_rounding
from torch import nn

from dust_rl.agents import VARIANTS, DustConfig, DustModel, random_batch, schedule_for

pytestmark = pytest.mark.usefixtures("one_thread")


def tiny(variant: str = "dust", **overrides) -> DustConfig:
    """Small config; H (6) differs from N_o (2x3) so that mixed-up token counts fail."""
    sizes = dict(
        variant=variant, action_dim=3, horizon=6, state_dim=5, vision_dim=7, vision_grid=(2, 3), cond_dim=11,
        d_model=32, n_heads=4, n_mmdit=2, n_dit=2,
    )
    return DustConfig(**{**sizes, **overrides})


def randomised(model: nn.Module, seed: int = 0) -> nn.Module:
    """Give every parameter random values, so zero-initialised (AdaLN-zero) paths carry signal."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=g))
    return model.eval()


def model_inputs(config: DustConfig, batch_size: int = 2, seed: int = 0, dtype: torch.dtype = torch.float32) -> dict:
    g = torch.Generator().manual_seed(seed)
    return dict(
        state=torch.randn(batch_size, config.state_dim, generator=g, dtype=dtype),
        cond=torch.randn(batch_size, 4, config.cond_dim, generator=g, dtype=dtype),
        action=torch.randn(batch_size, config.horizon, config.action_dim, generator=g, dtype=dtype),
        vision=torch.randn(batch_size, config.n_vision_tokens, config.vision_dim, generator=g, dtype=dtype),
    )


def float64_model(config: DustConfig) -> tuple[DustModel, dict]:
    """A randomised model and its inputs in float64, for claims that two code paths give the same output."""
    return randomised(DustModel(config)).double(), model_inputs(config, dtype=torch.float64)


def assert_same_trunk_output(model: DustModel, actual, expected) -> None:
    """Outputs of two code paths through ``model`` agree up to rounding (see conftest.rounding_tolerance).

    The longest sums run over the timestep embedder's sin-cos features or the MLP's hidden units; each block
    chains ~8 sums (norm, qkv, scores, softmax, values, out, fc1, fc2), the embedders and decoders ~8 more.
    """
    n_terms = max(model.time_embed.fc1.weight.shape[1], model.blocks[0].fc2.weight.shape[1])
    assert_close_up_to_rounding(actual, expected, n_terms=n_terms, depth=8 * len(model.blocks) + 8)


@pytest.mark.parametrize("variant", VARIANTS)
def test_shapes_of_loss_and_prediction(variant):
    config = tiny(variant)
    agent = DustModel(config)
    batch = random_batch(config, 3, n_cond_tokens=4, generator=torch.Generator().manual_seed(0))
    losses = agent.compute_loss(batch)
    assert losses.batch_size == torch.Size([])
    assert all(losses[k].shape == () and torch.isfinite(losses[k]) for k in ("loss", "loss_action", "loss_vision"))
    assert (losses["loss_vision"] > 0) == config.has_vision
    losses["loss"].backward()
    assert all(p.grad is not None for p in agent.parameters())

    out = agent.predict_action(batch.exclude("action_chunk", "future_tokens"), schedule_for(config))
    assert out.batch_size == torch.Size([3])
    assert out["action_chunk"].shape == (3, 6, 3)
    if config.has_vision:
        assert out["future_tokens"].shape == (3, 6, 7)
    else:
        assert "future_tokens" not in out.keys()


def test_default_size_matches_design():
    n_params = sum(p.numel() for p in DustModel(DustConfig()).parameters())
    assert 3.0e6 < n_params < 5.0e6  # docs/architecture.md: 3.85M for d=128, 4 MMDiT + 2 DiT blocks


def test_streams_keep_separate_weights_and_baselines_share():
    dust, joint = DustModel(tiny("dust")), DustModel(tiny("joint"))
    assert [b.kind for b in dust.blocks] == ["cross", "joint", "cross", "self"]
    assert [b.kind for b in joint.blocks] == ["cross", "self", "cross", "self"]  # same depth for the baselines
    for block in dust.blocks:
        assert all(layer.weight.shape[0] == 2 for layer in (block.qkv, block.out, block.fc1, block.fc2))
    assert dust.modulation.linear.weight.shape[0] == dust.time_embed.fc1.weight.shape[0] == 2
    assert all(block.qkv.weight.shape[0] == 1 for block in joint.blocks)


def _recording_model(variant: str):
    """A randomised model of ``variant``, its inputs and context, and the list its Modulation fills.

    Each forward appends (conditioning into the Modulation, vectors out), [S, B, T, d] each.
    """
    config = tiny(variant)
    model = randomised(DustModel(config))
    seen: list = []
    model.modulation.register_forward_hook(
        lambda mod, args, out: seen.append((args[0].clone(), torch.cat(out, -1).clone())))
    x = model_inputs(config)
    return config, model, x, model.encode_context(x["state"], x["cond"]), seen


@pytest.mark.parametrize("variant", ["dust", "mmdit_shared"])
def test_each_stream_adaln_sees_only_its_own_timestep(variant):
    config, model, x, ctx, seen = _recording_model(variant)
    tau_a = torch.tensor([0.3, 0.6])
    with torch.no_grad():
        if config.decoupled:
            model(ctx, x["action"], x["vision"], tau_a, torch.tensor([0.1, 0.2]))
            model(ctx, x["action"], x["vision"], tau_a, torch.tensor([0.8, 0.9]))
            (c1, mod1), (c2, mod2) = seen
            assert torch.equal(c1[0], c2[0]) and torch.equal(mod1[0], mod2[0])  # action stream unaffected by tau_o
            assert not torch.allclose(c1[1], c2[1]) and not torch.allclose(mod1[1], mod2[1])  # vision follows it
        else:
            model(ctx, x["action"], x["vision"], tau_a, tau_a)
            # Shared timestep, but still one embedder and modulation per stream.
            ((c, mod),) = seen
            assert not torch.allclose(c[0], c[1]) and not torch.allclose(mod[0], mod[1])
            with pytest.raises(ValueError):
                model(ctx, x["action"], x["vision"], tau_a, torch.tensor([0.1, 0.2]))


def test_single_stream_decoupled_conditions_each_token_on_its_modality():
    config, model, x, ctx, seen = _recording_model("decoupled")
    tau_a = torch.tensor([0.3, 0.6])
    with torch.no_grad():
        model(ctx, x["action"], x["vision"], tau_a, torch.tensor([0.1, 0.2]))
        model(ctx, x["action"], x["vision"], tau_a, torch.tensor([0.8, 0.9]))
    (_, mod1), (_, mod2) = seen
    n_a = 1 + config.horizon
    assert mod1.shape[:3] == (1, 2, n_a + config.n_vision_tokens)
    assert torch.equal(mod1[:, :, :n_a], mod2[:, :, :n_a])
    assert not torch.allclose(mod1[:, :, n_a:], mod2[:, :, n_a:])


def test_joint_attention_is_where_streams_meet():
    """In DUST the action output depends on the vision tokens (joint attention), and only
    the vision-stream blocks after the last joint block are skipped when actions are not needed."""
    config = tiny("dust")
    model, x = float64_model(config)  # skipping a stream changes matmul shapes, hence rounding
    ctx = model.encode_context(x["state"], x["cond"])
    tau = torch.tensor([0.3, 0.6], dtype=torch.float64)
    with torch.no_grad():
        va1, vo1 = model(ctx, x["action"], x["vision"], tau, tau)
        va2, _ = model(ctx, x["action"], x["vision"] + 1.0, tau, tau)
        va3, vo3 = model(ctx, x["action"], x["vision"], tau, tau, need_action=False)
        va4, vo4 = model(ctx, x["action"], x["vision"], tau, tau, need_vision=False)
    assert not torch.allclose(va1, va2)
    assert va3 is None and vo4 is None
    assert_same_trunk_output(model, vo3, vo1)
    assert_same_trunk_output(model, va4, va1)


@pytest.mark.parametrize("grid", [(2, 3), (3, 4), (1, 7)], ids=["fewer-vision", "more-vision", "equal"])
def test_stream_padding_is_never_attended_to(grid):
    """Streams are padded to a common length; more padding must not change any output."""
    config = tiny("dust", vision_grid=grid)
    model, x = float64_model(config)  # padding changes attention shapes, hence rounding
    ctx = model.encode_context(x["state"], x["cond"])
    tau_a, tau_o = torch.tensor([0.3, 0.6], dtype=torch.float64), torch.tensor([0.1, 0.9], dtype=torch.float64)
    with torch.no_grad():
        ref = model(ctx, x["action"], x["vision"], tau_a, tau_o)
        model.n_tokens += 5
        model.key_valid = torch.arange(model.n_tokens) < torch.tensor([[1 + config.horizon], [config.n_vision_tokens]])
        padded = model(ctx, x["action"], x["vision"], tau_a, tau_o)
    assert ref[1].shape == (2, grid[0] * grid[1], config.vision_dim)
    assert_same_trunk_output(model, padded, ref)  # one attended padding key moves outputs by ~3% of their scale


def test_masked_condition_tokens_are_ignored():
    config = tiny("dust")
    model, x = float64_model(config)
    mask = torch.tensor([[True, True, False, False], [True, True, True, False]])
    tau = torch.tensor([0.3, 0.6], dtype=torch.float64)
    noise = torch.randn(x["cond"].shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    changed_masked, changed_valid = x["cond"].clone(), x["cond"].clone()
    changed_masked[:, 3] += noise[:, 3]
    changed_valid[0, 1] += noise[0, 1]
    with torch.no_grad():
        ref = model(model.encode_context(x["state"], x["cond"], mask), x["action"], x["vision"], tau, tau)
        same = model(model.encode_context(x["state"], changed_masked, mask), x["action"], x["vision"], tau, tau)
        diff = model(model.encode_context(x["state"], changed_valid, mask), x["action"], x["vision"], tau, tau)
    assert_same_trunk_output(model, same, ref)
    assert not torch.allclose(diff[0][0], ref[0][0])


def test_context_is_reused_across_steps():
    """Cross-attention K/V are computed once per chunk: a context built once serves any tau."""
    config = tiny("dust")
    model = randomised(DustModel(config))
    x = model_inputs(config)
    ctx = model.encode_context(x["state"], x["cond"])
    n_cross = sum(b.kind == "cross" for b in model.blocks)
    assert sum(kv is not None for kv in ctx.cross_kv) == n_cross
    calls = []
    model.cond_in.register_forward_hook(lambda *args: calls.append(1))
    with torch.no_grad():
        for tau in (0.0, 0.5):
            t = torch.full((2,), tau)
            cached = model(ctx, x["action"], x["vision"], t, t)
            fresh = model(model.encode_context(x["state"], x["cond"]), x["action"], x["vision"], t, t)
            torch.testing.assert_close(cached, fresh, rtol=0, atol=0)
    assert len(calls) == 2  # only the two fresh contexts projected the condition tokens


@pytest.mark.parametrize("variant", ["dust", "joint"])
def test_action_free_samples_give_no_action_gradient(variant):
    config = tiny(variant)
    agent = DustModel(config)
    randomised(agent)
    batch = random_batch(config, 3, n_cond_tokens=4, generator=torch.Generator().manual_seed(1))
    batch["has_action"] = torch.tensor([True, False, False])
    batch["action_chunk"][2] = float("nan")  # placeholder actions must not leak in
    batch["action_chunk"].requires_grad_(True)
    losses = agent.compute_loss(batch, torch.Generator().manual_seed(2))
    assert torch.isfinite(losses["loss"])
    (grad,) = torch.autograd.grad(losses["loss_action"], batch["action_chunk"])
    assert (grad[0] != 0).any()
    assert (grad[1:] == 0).all()

    # The action values of an action-free sample do not change any loss.
    other = batch.clone()
    other["action_chunk"] = batch["action_chunk"].detach().clone()
    other["action_chunk"][1] += 3.0
    other_losses = agent.compute_loss(other, torch.Generator().manual_seed(2))
    torch.testing.assert_close(other_losses["loss"], losses["loss"])


def test_action_free_batch_trains_only_the_vision_stream():
    config = tiny("dust")
    agent = DustModel(config)
    randomised(agent)
    batch = random_batch(config, 2, n_cond_tokens=4, generator=torch.Generator().manual_seed(3))
    batch["has_action"] = torch.zeros(2, dtype=torch.bool)
    losses = agent.compute_loss(batch)
    assert losses["loss_action"].item() == 0.0 and losses["loss_vision"].item() > 0
    action_head = list(agent.action_out.parameters())
    grads = torch.autograd.grad(losses["loss"], action_head, allow_unused=True)
    assert all(g is None or (g == 0).all() for g in grads)


def test_padded_action_entries_are_excluded():
    config = tiny("dust", lambda_wm=0.0)
    agent = DustModel(config)
    randomised(agent)
    outputs = []
    agent.action_out.register_forward_hook(lambda mod, args, out: outputs.append(out) or out.retain_grad())
    batch = random_batch(config, 2, n_cond_tokens=4, generator=torch.Generator().manual_seed(4))
    batch["action_is_pad"] = torch.zeros(2, config.horizon, dtype=torch.bool)
    batch["action_is_pad"][:, -2:] = True
    agent.compute_loss(batch)["loss"].backward()
    (v_action,) = outputs
    assert (v_action.grad[:, -2:] == 0).all()
    assert (v_action.grad[:, :-2] != 0).all()


@pytest.mark.parametrize("variant", [v for v in VARIANTS if v != "action_only"])
def test_a_clamped_future_is_the_future_for_both_streams(variant):
    """One rule (module doc): the episode's last frame is the world model's target as it is the actions' input."""
    config = tiny(variant)
    agent = randomised(DustModel(config))
    batch = random_batch(config, 3, n_cond_tokens=4, generator=torch.Generator().manual_seed(5))
    flagged = batch.clone().set("future_is_clamped", torch.tensor([True, False, True]))
    losses, flagged_losses = (agent.compute_loss(b, torch.Generator().manual_seed(0)) for b in (batch, flagged))
    for name in ("loss_action", "loss_vision"):
        assert torch.equal(flagged_losses[name], losses[name])
    changed = flagged.clone()
    changed["future_tokens"][0] += 1.0  # the clamped window's frame is learnt from and acted on
    moved = agent.compute_loss(changed, torch.Generator().manual_seed(0))
    assert not torch.equal(moved["loss_vision"], losses["loss_vision"])
    assert not torch.equal(moved["loss_action"], losses["loss_action"])


def test_invalid_configs_are_rejected():
    with pytest.raises(ValueError):
        tiny("joint", sampler="async", vision_step_ratio=4)
    with pytest.raises(ValueError):
        tiny("action_only", sampler="sync")
    with pytest.raises(ValueError):
        tiny("nope")


@pytest.mark.parametrize("variant", ["dust", "mmdit_shared"])
def test_attention_over_a_batch_too_large_for_cuda_runs_in_slices(variant, monkeypatch):
    """Batches above CUDA's attention limit (65,535) are sliced: here the limit is lowered to 2, and a batch of
    5 chunks (10 stream rows, padded streams masked) gives the velocities of the unsliced computation."""
    from dust_rl.agents.model import mmdit

    torch.manual_seed(0)
    model = DustModel(DustConfig(variant=variant, d_model=32, n_heads=2, n_mmdit=2, n_dit=2)).double().eval()
    with torch.no_grad():
        for parameter in model.parameters():  # a new model's zero-initialised gates would hide the attention
            parameter.normal_(0.0, 0.3)
    batch = random_batch(model.config, 5, 6, torch.Generator().manual_seed(1)).double()
    ctx = model.encode_context(batch["state"], batch["cond_tokens"])
    tau = torch.rand(5, dtype=torch.float64)
    inputs = (ctx, batch["action_chunk"], batch["future_tokens"], tau, tau)
    whole = model(*inputs)
    monkeypatch.setattr(mmdit, "MAX_ATTENTION_BATCH", 2)
    sliced = model(*inputs)
    for got, expected in zip(sliced, whole):
        assert_close_up_to_rounding(got, expected, n_terms=model.config.d_model, depth=6)
