"""Atomic single-file checkpoints with a kind tag and a format version.

A policy or encoder checkpoint is one ``torch.save`` file holding only
tensors, numbers, strings, lists and dicts, so it loads with
``weights_only=True`` (no code runs on load). It is written to a temp file in
the same folder, fsynced and moved over the target with ``os.replace``: a
killed writer leaves the old file or the new one, never half of one.
"""

from __future__ import annotations

import os
import pathlib
import uuid

import torch

FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, of another kind, or does not fit what it is loaded into."""


def save_checkpoint(payload: dict, path: str | pathlib.Path, kind: str) -> pathlib.Path:
    """Write ``payload`` tagged with ``kind`` atomically to ``path``; returns the path."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save({"kind": kind, "format_version": FORMAT_VERSION, **payload}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | pathlib.Path, kind: str) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`, checking its kind and version.

    Raises:
        CheckpointError: the file is missing, corrupt, of another kind or another format version.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"{path}: corrupt or not a torch checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(payload, dict) or payload.get("kind") != kind:
        found = payload.get("kind") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{path}: expected a {kind!r} checkpoint, found {found!r}")
    if payload.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {payload.get('format_version')!r}; "
                              f"this dust-rl reads version {FORMAT_VERSION}")
    return payload
