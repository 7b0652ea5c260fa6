"""Keypoints learned end to end from raw frames: the shift augmentation, the network, the batches that feed it."""

from __future__ import annotations

import pytest
import torch
from test_agents_policy import observation, tiny_policy

from dust_rl.agents import make_policy
from dust_rl.agents.heads.pixel_keypoints import MAX_SHIFT, PixelKeypoints, random_shift
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache, dataset_policy_kwargs

pytestmark = pytest.mark.usefixtures("one_thread")


def test_random_shift_moves_each_image_by_its_own_offset():
    images = torch.rand(6, 3, 7, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    shift = 2
    shifted = random_shift(images, shift, torch.Generator().manual_seed(1))
    dy, dx = torch.randint(0, 2 * shift + 1, (2, 6), generator=torch.Generator().manual_seed(1)).tolist()
    padded = torch.nn.functional.pad(images, (shift,) * 4, mode="replicate")
    for i in range(6):  # a plain crop of the replicate-padded image, exactly
        assert torch.equal(shifted[i], padded[i, :, dy[i]:dy[i] + 7, dx[i]:dx[i] + 9])
    assert len({(y, x) for y, x in zip(dy, dx)}) > 1  # offsets differ between images
    assert torch.equal(random_shift(images, 0), images)


def test_network_shifts_only_when_asked_and_reproducibly():
    net = PixelKeypoints(5)
    frames = torch.randint(0, 256, (3, 3, 32, 32), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    coordinates, attended = net(frames)
    assert coordinates.shape == (3, 5, 2) and attended.shape == (3, 5, PixelKeypoints.feature_dim)
    assert coordinates.abs().max() <= 1
    assert torch.equal(net(frames)[0], coordinates)  # acting: no augmentation
    first = net(frames, True, torch.Generator().manual_seed(2))[0]
    assert torch.equal(net(frames, True, torch.Generator().manual_seed(2))[0], first)
    assert not torch.equal(first, coordinates) and MAX_SHIFT > 0


def test_pixel_keypoints_need_the_frames(tiny_encoder, minilm):
    policy = tiny_policy("dust", tiny_encoder, minilm, keypoints=2, keypoint_source="pixels")
    features = policy.observation_features(observation())
    assert features.get("pixels").shape == (2, 2, 3, 32, 32) and features.get("pixels").dtype == torch.uint8
    batch = features.set("action_chunk", torch.randn(2, 6, 3)).set(
        "future_tokens", policy.future_targets(features.get("image_tokens")))
    policy.compute_loss(batch)["loss"].backward()
    assert all(p.grad is not None for p in policy.condition.keypoints.parameters())
    with pytest.raises(ValueError, match="no 'pixels'"):
        policy.compute_loss(batch.exclude("pixels"))
    frozen_source = tiny_policy("dust", tiny_encoder, minilm, keypoints=2)
    assert "pixels" not in frozen_source.observation_features(observation()).keys()


def test_feature_batches_carry_the_window_frames(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, keypoints=2,
                         keypoint_source="pixels")
    windows = DemoWindows(dataset, horizon=6, batch_size=5, images=False).sample()
    pixels = FeatureCache(dataset, policy, progress=False).batch(windows).get("pixels")
    rows = windows.get("index")
    for c, cam in enumerate(policy.cameras):
        assert torch.equal(pixels[:, c], dataset.data.get(("observation", "image", cam))[rows])
