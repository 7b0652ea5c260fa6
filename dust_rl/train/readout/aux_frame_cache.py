"""Rendered aux frames kept beside the dataset, so runs that ask for the same frames render them once.

Why: a run's aux frames (:mod:`dust_rl.train.readout.aux_frames`) depend only on the
dataset's env and tasks, the policy's cameras and the frame settings and seed,
yet every run rendered its own: press_button frames took 0.12 s each with two
trainings beside them on the 2 cores (8,000 frames: 16 min), and every cell of ``dust-rl bench suite``
with the same training seed rendered the same frames again. Measured with::

    .venv/bin/python -c "import time; from dust_rl.train.readout.aux_frames import render_aux_frames as r; \
        t = time.time(); r('DustFranka-v0', {}, ['press_button'], ['front', 'wrist'], 200, 12, progress=False); \
        print(time.time() - t)"
 They are now
stored in ``<dataset>/aux_frames/<key>.npz`` (the key hashes every setting
that shapes a frame) and read back by any later run that asks for the same.
The file holds plain arrays (the frames as uint8, so a cached run encodes
exactly what a fresh one would), is read with ``allow_pickle=False``, and is
written beside its final name and renamed when complete. 8,000 frames of two
128 px cameras take 788 MB.

A token read-out reads the frames through the frozen image encoder, and
every run encoded them again: 8,000 frames of two cameras took 3.3 min on one
thread beside two trainings (EfficientNet-Lite0 at stride 8, 16x16 tokens; 256
frames timed, scaled to 8,000; 2.1 min beside one), part of every bench cell's start. Measured with::

    .venv/bin/python -c "import time, torch; torch.set_num_threads(1); from dust_rl.agents import make_policy; \
        from dust_rl.train.readout.aux_frames import encode_frames; p = make_policy(image_encoder= \
        'efficientnet-lite0-s8', cond_grid=(8, 8), readout='tokens', readout_grid=(16, 16), \
        cameras=['front', 'wrist'], state_dim=17, action_dim=7); \
        f = torch.randint(0, 255, (256, 2, 3, 128, 128), dtype=torch.uint8); t = time.time(); \
        encode_frames(p, f); print((time.time() - t) * 8000 / 256)"

The tokens are stored beside their frames
(``<key>.tokens-<encoder key>.npy``, float32 as encoded, 655 MB for those
frames), keyed by the image encoder's description, a digest of its weights
and the token grid, so any run with the same frozen encoder reads them back
(the stored ones: an encoding on another machine or thread count may differ in
the last bits).
"""

from __future__ import annotations

import hashlib
import json
import pathlib
import zipfile
from typing import NamedTuple

import numpy as np
import torch
from tensordict import TensorDict

from dust_rl.agents import DustPolicy
from dust_rl.data import DatasetError
from dust_rl.data.features import hash_weights
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY, STATE_KEY, TASK_INDEX_KEY
from dust_rl.storage.atomic_files import atomic_write
from dust_rl.storage.cache_files import cached, record_cache
from dust_rl.train.readout.aux_frames import encode_frames, render_aux_frames

# Raise when what render_aux_frames draws changes, so older files are not read as current (2: the arm placed; 3: the
# robot state kept).
FORMAT = 3
TOKEN_FORMAT = 1  # raise when how an image encoder turns frames into tokens changes


class StoredFrames(NamedTuple):
    """:func:`~.aux_frames.render_aux_frames`' frames and instructions, and the file that keeps them."""

    rows: TensorDict
    instructions: list[str]
    path: pathlib.Path


def cached_aux_frames(folder: pathlib.Path, env_id: str, env_kwargs: dict, tasks: list[str], cameras: list[str],
                      count: int, env_state_width: int, progress: bool = True,
                      **settings) -> StoredFrames:
    """:func:`~.aux_frames.render_aux_frames`, read from ``folder`` when an earlier run rendered the same.

    Args:
        folder: where the frames are kept (``<dataset>/aux_frames``).
        env_id, env_kwargs, tasks, cameras, count, env_state_width, progress, settings: as
            :func:`~.aux_frames.render_aux_frames` takes them.

    Raises:
        DatasetError: a stored file that does not hold what its name promises (delete it to render again).
    """
    key = {"format": FORMAT, "env_id": env_id, "env_kwargs": env_kwargs, "tasks": tasks, "cameras": cameras,
           "count": count, "env_state_width": env_state_width, **settings}
    path = folder / f"{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]}.npz"
    if cached(path):
        return StoredFrames(*_read(path, cameras, count, env_state_width), path)
    rows, instructions = render_aux_frames(env_id, env_kwargs, tasks, cameras, count, env_state_width,
                                           progress=progress, **settings)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as file:
        np.savez(file, **{f"image_{i}": rows.get((*IMAGE_KEY, cam)).numpy() for i, cam in enumerate(cameras)},
                 env_state=rows.get(ENV_STATE_KEY).numpy(), state=rows.get(STATE_KEY).numpy(),
                 task_index=rows.get(TASK_INDEX_KEY).numpy(),
                 instructions=np.array(instructions, dtype=str))
    record_cache(path)
    return StoredFrames(rows, instructions, path)


def cached_frame_tokens(frames_file: pathlib.Path, policy: DustPolicy, frames: torch.Tensor) -> torch.Tensor:
    """:func:`~.aux_frames.encode_frames` of the frames stored in ``frames_file``, read from beside that
    file when an earlier run encoded them with the same image encoder and token grid.

    Raises:
        DatasetError: a stored file that does not hold what its name promises (delete it to encode again).
    """
    encoder = policy.backbone.image
    digest = hashlib.sha256(json.dumps({"format": TOKEN_FORMAT, "grid": list(policy.config.token_grid),
                                        "encoder": encoder.reference()}, sort_keys=True).encode())
    hash_weights(digest, encoder)
    path = frames_file.with_name(f"{frames_file.stem}.tokens-{digest.hexdigest()[:16]}.npy")
    if not cached(path):
        tokens = encode_frames(policy, frames)
        with atomic_write(path, "wb") as file:
            np.save(file, tokens.numpy(), allow_pickle=False)
        record_cache(path)
        return tokens
    try:
        tokens = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise DatasetError(f"{path}: unreadable aux-frame tokens ({err}); delete the file to encode them "
                           "again") from err
    if tokens.dtype != np.float32 or tokens.ndim != 4 or tokens.shape[:2] != tuple(frames.shape[:2]):
        raise DatasetError(f"{path}: aux-frame tokens are {tokens.dtype} {tokens.shape}, expected float32 "
                           f"{tuple(frames.shape[:2])} + (tokens, channels); delete the file to encode them again")
    return torch.from_numpy(tokens)


def _read(path: pathlib.Path, cameras: list[str], count: int, env_state_width: int) -> tuple[TensorDict, list[str]]:
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:
        raise DatasetError(f"{path}: unreadable aux frames ({err}); delete the file to render them again") from err
    expected = {**{f"image_{i}": (np.uint8, (count, 3)) for i in range(len(cameras))},
                "env_state": (np.float32, (count, env_state_width)), "state": (np.float32, (count,)),
                "task_index": (np.int64, (count,)),
                "instructions": (np.str_, (count,))}
    for name, (dtype, leading) in expected.items():
        array = arrays.get(name)
        if array is None or not np.issubdtype(array.dtype, dtype) or array.shape[:len(leading)] != leading:
            found = "missing" if array is None else f"{array.dtype} {array.shape}"
            raise DatasetError(f"{path}: aux frames' {name} is {found}, expected {np.dtype(dtype).name} "
                               f"{leading}...; delete the file to render them again")
    rows = TensorDict({**{(*IMAGE_KEY, cam): torch.from_numpy(arrays[f"image_{i}"]) for i, cam in enumerate(cameras)},
                       ENV_STATE_KEY: torch.from_numpy(arrays["env_state"]),
                       STATE_KEY: torch.from_numpy(arrays["state"]),
                       TASK_INDEX_KEY: torch.from_numpy(arrays["task_index"])}, batch_size=[count])
    return rows, arrays["instructions"].tolist()
