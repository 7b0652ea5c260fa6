"""Core wiring on real demonstrations: encoder pretraining, cached frozen features, a tiny DUST that learns."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from conftest import rounding_tolerance

from dust_rl.agents import AutoencoderConfig, ConvAutoencoder, load_image_encoder, make_policy
from dust_rl.agents.encoders.backbone import DEFAULT_IMAGE_ENCODER_FILE
from dust_rl.cli import main
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache, dataset_policy_kwargs, env_state_width
from dust_rl.storage.cache_files import record_cache, record_path, signing_key
from dust_rl.storage.checkpoint_dirs import file_sha256
from dust_rl.train.pretrain_encoder import FramePool, pretrain_encoder

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_AE = AutoencoderConfig(image_size=32, dim=16, width=8, max_width=16)


@pytest.fixture(scope="module")
def dataset(demo_dir):
    return DemoDataset(demo_dir)


def small_policy(dataset, encoder, text, variant="dust"):
    return make_policy(variant, image_encoder=encoder, text_encoder=text, **dataset_policy_kwargs(dataset),
                       horizon=8, d_model=64, n_heads=4, n_mmdit=2, n_dit=1)


def test_pretraining_reconstructs_held_out_frames(dataset, tmp_path):
    report = pretrain_encoder([dataset], tmp_path / "enc.pt", TINY_AE, steps=150, batch_size=16, lr=3e-3,
                              warmup=5, holdout_every=3, progress=False)
    pool = FramePool([dataset], holdout_every=3)
    frames = pool.heldout_frames(256, 32, torch.Generator().manual_seed(0))
    torch.manual_seed(0)
    with torch.no_grad():
        untrained = ConvAutoencoder(TINY_AE).reconstruction_loss(frames).item()
    assert report.heldout_loss < 0.5 * untrained, (report.heldout_loss, untrained)
    encoder = load_image_encoder(report.path)
    with torch.no_grad():
        tokens = encoder.feature_map(pool.sample(256, 32, torch.Generator().manual_seed(1)))
    channels = tokens.transpose(0, 1).flatten(1)  # standardised with training-frame statistics
    assert channels.mean(1).abs().max() < 0.3 and (channels.std(1) - 1).abs().max() < 0.3


def test_committed_default_encoder_fits_env_frames(dataset):
    encoder = load_image_encoder(DEFAULT_IMAGE_ENCODER_FILE)  # what make_policy uses by default
    frames = FramePool([dataset], holdout_every=0).sample(64, encoder.image_size, torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert encoder.reconstruction_loss(frames).item() < 0.01  # 32 px frames, upsampled to its 128 px
        tokens = encoder.feature_map(frames)
    assert tokens.shape == (64, 64, 4, 4) and 0.5 < tokens.std().item() < 1.5


def test_pretrain_encoder_command(demo_dir, tmp_path, capsys):
    out = tmp_path / "enc.pt"
    args = ["pretrain-encoder", "--dataset", str(demo_dir), "--out", str(out), "--steps", "2", "--batch-size", "4",
            "--image-size", "32", "--width", "8", "--dim", "16"]
    with pytest.raises(SystemExit, match="dust-rl: error: unknown device 'tpu'"):
        main([*args, "--runtime.device", "tpu"])
    main([*args, "--runtime.device", "cpu"])
    assert "2 steps" in capsys.readouterr().out
    assert load_image_encoder(out).config == AutoencoderConfig(image_size=32, dim=16, width=8)
    payload = torch.load(out, weights_only=True)
    assert payload["info"]["command"].startswith("dust-rl pretrain-encoder --dataset")


def test_a_shipped_cache_whose_record_was_written_anew_is_built_again(demo_dir, tmp_path, tiny_encoder, minilm,
                                                                      monkeypatch, capsys):
    """A digest proves integrity, not origin: a poisoned cache with its digest recomputed, or signed with another
    user's key (a copied dataset), is not read."""
    dataset = DemoDataset(shutil.copytree(demo_dir, tmp_path / "ds"))
    policy = small_policy(dataset, tiny_encoder, minilm)

    def features() -> FeatureCache:
        return FeatureCache(dataset, policy, batch_size=32, progress=False, store=True)

    cache = features()
    clean, path = cache.image_tokens.clone(), cache.path

    def poison() -> None:
        np.save(path, np.zeros_like(np.load(path)), allow_pickle=False)

    poison()
    record_path(path).write_text(json.dumps({"size": path.stat().st_size, "sha256": file_sha256(path)}))
    assert torch.equal(features().image_tokens, clean)
    poison()
    with monkeypatch.context() as elsewhere:  # the record of another machine's user, as a copied dataset brings
        elsewhere.setenv("XDG_CONFIG_HOME", str(tmp_path / "elsewhere"))
        signing_key.cache_clear()
        record_cache(path)
    signing_key.cache_clear()
    assert torch.equal(features().image_tokens, clean)
    assert capsys.readouterr().err.count("(its record is not signed here); building it again") == 2
    assert features().path == path  # built again, and trusted now
    assert "cached elsewhere" not in capsys.readouterr().err


def test_feature_cache_encodes_each_row_once(dataset, tiny_encoder, minilm, monkeypatch):
    policy = small_policy(dataset, tiny_encoder, minilm)
    encoded = []
    feature_map = tiny_encoder.feature_map
    monkeypatch.setattr(tiny_encoder, "feature_map", lambda x: (encoded.append(len(x)), feature_map(x))[1])
    cache = FeatureCache(dataset, policy, batch_size=32, progress=False)
    assert sum(encoded) == 2 * len(dataset)  # every row, both cameras, once
    assert cache.image_tokens.shape == (len(dataset), 2, 16, 16)

    windows = DemoWindows(dataset, horizon=8, batch_size=16).sample()
    batch = cache.batch(windows)
    assert sum(encoded) == 2 * len(dataset)  # batches are lookups
    assert batch["action_chunk"].shape == (16, 8, 7) and batch["future_tokens"].shape == (16, 16, 16)
    # Lookups equal encoding the window's own frames: current ones as condition, the t+H front frame as target.
    # Up to rounding, as batch sizes differ: the encoder's longest sums are group norms over 16x16 maps, and
    # ~8 convolutions, norms and the standardisation run in sequence; the cache keeps float16 copies (half
    # an ulp of float16 more).
    for cached, encoded_now in [(batch["image_tokens"], policy.image_features(windows)),
                                (batch["future_tokens"], policy.image_features(windows["future"])[:, 0])]:
        scale = encoded_now.abs().max().item()
        atol = rounding_tolerance(torch.float32, 256, 8, scale) + torch.finfo(torch.float16).eps * scale
        torch.testing.assert_close(cached, encoded_now, rtol=0, atol=atol)
    text, mask = policy.backbone.text_tokens(list(windows["language_instruction"]))
    assert torch.equal(batch["text_tokens"], text) and torch.equal(batch["text_mask"], mask)
    normalizer = policy.normalizer
    torch.testing.assert_close(normalizer.denormalize_action(batch["action_chunk"]), windows["vla_action", "chunk"])
    torch.testing.assert_close(batch["state"] * normalizer.state_std + normalizer.state_mean,
                               windows["observation", "state"])


def test_tiny_dust_learns_from_demonstrations(dataset, tiny_encoder, minilm):
    torch.manual_seed(0)
    policy = small_policy(dataset, tiny_encoder, minilm)
    cache = FeatureCache(dataset, policy, progress=False)
    windows = DemoWindows(dataset, horizon=8, batch_size=32)
    fixed = cache.batch(next(windows.iterate(64)))

    def fixed_draw_losses() -> dict[str, float]:
        with torch.no_grad():
            losses = policy.compute_loss(fixed, torch.Generator().manual_seed(123))
        return {k: v.item() for k, v in losses.items()}

    before = fixed_draw_losses()
    optimizer = torch.optim.AdamW(policy.trainable_parameters(), lr=2e-3)
    generator = torch.Generator().manual_seed(0)
    for _ in range(80):
        loss = policy.compute_loss(cache.batch(windows.sample()), generator)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = fixed_draw_losses()
    assert after["loss"] < 0.6 * before["loss"], (before, after)
    assert after["loss_action"] < before["loss_action"] and after["loss_vision"] < before["loss_vision"]
    # The trained policy acts on raw dataset observations.
    plan = policy.eval().plan(next(windows.iterate(4)))
    assert plan["action_chunk"].shape == (4, 8, 7) and torch.isfinite(plan["action_chunk"]).all()
    assert policy.backbone.image.decode(plan["future_tokens"]).shape == (4, 3, 32, 32)  # predicted future, rendered


def test_stored_features_are_reused(demo_dir, tiny_encoder, minilm, tmp_path, monkeypatch):
    import shutil

    dataset = DemoDataset(shutil.copytree(demo_dir, tmp_path / "data"))
    policy = small_policy(dataset, tiny_encoder, minilm)
    first = FeatureCache(dataset, policy, progress=False, store=True)
    assert first.path.parent == dataset.root / "features" and first.path.is_file()
    monkeypatch.setattr(tiny_encoder, "feature_map", lambda x: pytest.fail("encoded again"))
    second = FeatureCache(dataset, policy, progress=False, store=True)
    assert second.path == first.path and torch.equal(second.image_tokens, first.image_tokens)
    with torch.no_grad():  # other encoder weights: another key, so stale features are never read
        next(tiny_encoder.parameters()).add_(1.0)
    monkeypatch.undo()
    assert FeatureCache(dataset, policy, progress=False, store=True).path != first.path


def test_feature_cache_keeps_augmented_views(dataset, tiny_encoder, minilm):
    policy = small_policy(dataset, tiny_encoder, minilm)
    plain = FeatureCache(dataset, policy, batch_size=32, progress=False)
    augmented = FeatureCache(dataset, policy, batch_size=32, progress=False, views=3)
    assert augmented.views.shape == (3, *plain.image_tokens.shape)
    assert torch.equal(augmented.image_tokens, plain.image_tokens)  # view 0: the frames themselves
    assert not torch.equal(augmented.views[1], augmented.views[0])
    assert not torch.equal(augmented.views[1], augmented.views[2])
    again = FeatureCache(dataset, policy, batch_size=32, progress=False, views=3)
    assert torch.equal(again.views, augmented.views)  # seeded: the same views on every rebuild
    windows = DemoWindows(dataset, horizon=8, batch_size=64).sample()
    batch = augmented.batch(windows)
    # Targets always come from view 0; conditions from a view drawn per window, so both kinds appear.
    torch.testing.assert_close(batch["future_tokens"], plain.batch(windows)["future_tokens"])
    from_view0 = (batch["image_tokens"] == plain.image_tokens[windows["index"]].float()).flatten(1).all(1)
    assert 0 < from_view0.sum() < len(from_view0)


def test_stored_readout_estimates_are_the_live_ones_of_the_unaugmented_frames(dataset, tiny_encoder, minilm):
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=8, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         aux_state_dim=env_state_width(dataset), lambda_aux=1.0, aux_state_input=True)
    policy.readout.frame_modules().requires_grad_(False)
    features = FeatureCache(dataset, policy, batch_size=32, progress=False, views=3)
    windows = DemoWindows(dataset, horizon=8, batch_size=64).sample()
    live = features.batch(windows)
    features.store_readout_estimates(chunk=37)  # chunks that do not divide the rows
    stored = features.batch(windows)
    on_frames = live.clone().set("image_tokens", features.image_tokens[windows["index"]].float())
    torch.manual_seed(0)
    expected = policy.compute_loss(on_frames)
    torch.manual_seed(0)
    got = policy.compute_loss(stored)  # the trunk reads the stored estimate, not the augmented view's
    # Tolerance: float32 rounding of the read-out at another batch size, carried through the trunk.
    tolerance = rounding_tolerance(torch.float32, policy.config.d_model, depth=policy.config.n_mmdit + 1)
    torch.testing.assert_close(got["loss_aux"], expected["loss_aux"], rtol=tolerance, atol=tolerance)
    torch.testing.assert_close(got["loss"], expected["loss"], rtol=tolerance, atol=tolerance)
    assert not torch.allclose(policy.compute_loss(live)["loss_aux"], got["loss_aux"])  # an augmented view differs


def test_augment_frames_shifts_and_jitters_within_bounds():
    from dust_rl.data.augment import MAX_SHIFT, augment_frames

    frames = torch.zeros(4, 3, 32, 32, dtype=torch.uint8)
    frames[:, :, 12:20, 12:20] = 200  # a bright square in the middle
    out = augment_frames(frames, torch.Generator().manual_seed(0))
    assert out.shape == frames.shape and out.dtype == torch.uint8
    assert torch.equal(out, augment_frames(frames, torch.Generator().manual_seed(0)))
    for image in out:
        ys, xs = torch.nonzero(image[0] > 100, as_tuple=True)
        assert abs(ys.float().mean().item() - 15.5) <= MAX_SHIFT and abs(xs.float().mean().item() - 15.5) <= MAX_SHIFT


def test_encoder_check_command_writes_probe_per_camera(demo_dir, tmp_path, capsys):
    main(["encoder", "check", "--dataset", str(demo_dir), "--image-encoder", "efficientnet-lite0", "--every", "3",
          "--out", str(tmp_path / "check")])
    report = json.loads((tmp_path / "check" / "probe.json").read_text())
    state = DemoDataset(demo_dir).data.get(("observation", "environment_state"))[::3]
    varying = (state.std(0) > 0).nonzero().flatten().tolist()
    assert set(report["cameras"]) == {"front", "wrist"}
    for result in report["cameras"].values():
        assert result["columns"] == varying and len(result["r2"]) == len(varying)
        assert all(math.isfinite(r) for r in result["r2"])
        assert result["heldout_rows"] > 0 and result["train_rows"] > result["heldout_rows"]
    assert (tmp_path / "check" / "probe.png").stat().st_size > 0
    assert "front: held-out R^2" in capsys.readouterr().out


def test_encoder_info_command_reports_the_grid_and_cache_size(capsys):
    main(["encoder", "info", "--image-encoder", "efficientnet-lite0", "--frames", "2"])
    printed = capsys.readouterr().out
    # 8x8 tokens of 112 channels in float16: 1,000 frames hold 1000 * 64 * 112 * 2 bytes = 13.7 MiB.
    assert "128 px -> 8x8 tokens of 112" in printed and "13.7 MiB per 1,000 frames" in printed
    assert float(printed.split(" ms/frame")[0].rsplit(" ", 1)[-1]) > 0
