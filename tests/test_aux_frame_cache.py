"""The aux-frame store: a second run asking for the same frames (or their tokens) reads them; other settings
render (or encode) their own."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from conftest import DEMO_ENV_KWARGS

from dust_rl.agents import make_policy
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.storage.cache_files import record_cache
from dust_rl.train.readout import aux_frame_cache
from dust_rl.train.readout.aux_frame_cache import cached_aux_frames, cached_frame_tokens
from dust_rl.train.readout.aux_frames import encode_frames, render_aux_frames

pytestmark = pytest.mark.usefixtures("one_thread")
ARGS = ("DustFranka-v0", DEMO_ENV_KWARGS, ["pick_place", "push"], ["front", "wrist"], 3, 13)


def test_stored_frames_are_the_rendered_ones_and_keyed_by_their_settings(tmp_path, monkeypatch):
    first, instructions, _ = cached_aux_frames(tmp_path, *ARGS, seed=1, progress=False)
    (stored,) = tmp_path.glob("*.npz")
    fresh, fresh_instructions = render_aux_frames(*ARGS, seed=1, progress=False)

    def render_again(*args, **kwargs):
        raise AssertionError("the stored frames were rendered again")

    with monkeypatch.context() as patch:
        patch.setattr(aux_frame_cache, "render_aux_frames", render_again)
        again, instructions_again, _ = cached_aux_frames(tmp_path, *ARGS, seed=1, progress=False)
    assert (again == first).all() and (again == fresh).all()  # read back bit for bit, as a fresh render
    assert instructions_again == instructions == fresh_instructions
    assert list(tmp_path.glob("*.npz")) == [stored]
    other = cached_aux_frames(tmp_path, *ARGS, seed=2, progress=False).rows
    assert len(list(tmp_path.glob("*.npz"))) == 2 and not (other == first).all()
    close_ups = cached_aux_frames(tmp_path, *ARGS, seed=1, close_up_fraction=1.0, progress=False).rows
    assert len(list(tmp_path.glob("*.npz"))) == 3 and not (close_ups == first).all()


def test_a_damaged_store_is_named(tmp_path):
    cached_aux_frames(tmp_path, *ARGS, progress=False)
    (stored,) = tmp_path.glob("*.npz")
    stored.write_bytes(stored.read_bytes()[:100])
    with pytest.raises(DatasetError, match="this cache changed since it was written .*; delete it"):
        cached_aux_frames(tmp_path, *ARGS, progress=False)
    record_cache(stored)  # damaged before its record was written
    with pytest.raises(DatasetError, match="unreadable aux frames.*delete the file"):
        cached_aux_frames(tmp_path, *ARGS, progress=False)
    with stored.open("wb") as file:  # readable, but not the frames its name promises
        np.savez(file, image_0=np.zeros((3, 3, 8, 8), np.uint8), image_1=np.zeros((2, 3, 8, 8), np.uint8))
    record_cache(stored)
    with pytest.raises(DatasetError, match=r"image_1 is uint8 \(2, 3, 8, 8\), expected uint8 \(3, 3\)"):
        cached_aux_frames(tmp_path, *ARGS, progress=False)


def test_stored_tokens_are_the_encoded_ones_and_keyed_by_encoder_weights_and_grid(tmp_path, monkeypatch, demo_dir,
                                                                                    tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)

    def token_policy(encoder, grid):
        return make_policy(image_encoder=encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                           horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                           cond_grid=(2, 2), vision_grid=(2, 2), readout_grid=grid,
                           aux_state_dim=env_state_width(dataset), lambda_aux=1.0)

    stored = cached_aux_frames(tmp_path, *ARGS, progress=False)
    policy = token_policy(tiny_encoder, (4, 4))
    frames = policy.frames(stored.rows)
    first = cached_frame_tokens(stored.path, policy, frames)
    assert torch.equal(first, encode_frames(policy, frames))

    def encode_again(*args, **kwargs):
        raise AssertionError("the stored tokens were encoded again")

    with monkeypatch.context() as patch:
        patch.setattr(aux_frame_cache, "encode_frames", encode_again)
        assert torch.equal(cached_frame_tokens(stored.path, policy, frames), first)  # read back bit for bit
    (tokens_file,) = tmp_path.glob("*.tokens-*.npy")
    coarser = token_policy(tiny_encoder, (2, 2))
    assert cached_frame_tokens(stored.path, coarser, frames).shape[2] == 4
    retrained = copy.deepcopy(tiny_encoder)
    with torch.no_grad():
        next(retrained.parameters()).add_(1.0)
    assert not torch.equal(cached_frame_tokens(stored.path, token_policy(retrained, (4, 4)), frames), first)
    assert len(list(tmp_path.glob("*.tokens-*.npy"))) == 3

    np.save(tokens_file, first.numpy()[:2])  # readable, but not the frames' tokens
    with pytest.raises(DatasetError, match="this cache changed since it was written"):
        cached_frame_tokens(stored.path, policy, frames)
    record_cache(tokens_file)  # as if written so
    with pytest.raises(DatasetError, match=r"tokens are float32 \(2, 2, 16, 16\), expected float32 \(3, 2\)"):
        cached_frame_tokens(stored.path, policy, frames)
    tokens_file.write_bytes(b"\x93NUMPY")
    record_cache(tokens_file)
    with pytest.raises(DatasetError, match="unreadable aux-frame tokens.*delete the file"):
        cached_frame_tokens(stored.path, policy, frames)
