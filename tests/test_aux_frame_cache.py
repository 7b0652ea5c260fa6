"""The aux-frame store: a second run asking for the same frames reads them; other settings render their own."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DEMO_ENV_KWARGS

from dust_rl import aux_frame_cache
from dust_rl.aux_frame_cache import cached_aux_frames
from dust_rl.aux_frames import render_aux_frames
from dust_rl.data import DatasetError

pytestmark = pytest.mark.usefixtures("one_thread")
ARGS = ("DustFranka-v0", DEMO_ENV_KWARGS, ["pick_place", "push"], ["front", "wrist"], 3, 9)


def test_stored_frames_are_the_rendered_ones_and_keyed_by_their_settings(tmp_path, monkeypatch):
    first, instructions = cached_aux_frames(tmp_path, *ARGS, seed=1, progress=False)
    (stored,) = tmp_path.iterdir()
    fresh, fresh_instructions = render_aux_frames(*ARGS, seed=1, progress=False)

    def render_again(*args, **kwargs):
        raise AssertionError("the stored frames were rendered again")

    with monkeypatch.context() as patch:
        patch.setattr(aux_frame_cache, "render_aux_frames", render_again)
        again, instructions_again = cached_aux_frames(tmp_path, *ARGS, seed=1, progress=False)
    assert (again == first).all() and (again == fresh).all()  # read back bit for bit, as a fresh render
    assert instructions_again == instructions == fresh_instructions
    assert list(tmp_path.iterdir()) == [stored]
    other, _ = cached_aux_frames(tmp_path, *ARGS, seed=2, progress=False)
    assert len(list(tmp_path.iterdir())) == 2 and not (other == first).all()


def test_a_damaged_store_is_named(tmp_path):
    cached_aux_frames(tmp_path, *ARGS, progress=False)
    (stored,) = tmp_path.iterdir()
    stored.write_bytes(stored.read_bytes()[:100])
    with pytest.raises(DatasetError, match="unreadable aux frames.*delete the file"):
        cached_aux_frames(tmp_path, *ARGS, progress=False)
    with stored.open("wb") as file:  # readable, but not the frames its name promises
        np.savez(file, image_0=np.zeros((3, 3, 8, 8), np.uint8), image_1=np.zeros((2, 3, 8, 8), np.uint8))
    with pytest.raises(DatasetError, match=r"image_1 is uint8 \(2, 3, 8, 8\), expected uint8 \(3, 3\)"):
        cached_aux_frames(tmp_path, *ARGS, progress=False)
