"""Atomic file writes: a killed writer leaves the old file or the new one, never half of one.

Content goes to a temp file in the target's folder (same file system, so the final
``os.replace`` is atomic), is fsynced, and then replaces the target. Datasets,
reports, summaries and run configs are all written this way.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import uuid
from collections.abc import Iterator
from typing import IO


@contextlib.contextmanager
def atomic_write(path: str | pathlib.Path, mode: str = "w") -> Iterator[IO]:
    """Open a temp file beside ``path`` for writing; on a clean exit it replaces ``path``.

    Args:
        path: the file to (re)place; its folder must exist.
        mode: ``"w"`` (text) or ``"wb"`` (bytes).

    If the body raises, ``path`` is untouched and the temp file removed.
    """
    path = pathlib.Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | pathlib.Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_write(path) as f:
        f.write(text)


def write_json_atomic(path: str | pathlib.Path, payload: object, indent: int = 1) -> None:
    """Write ``payload`` as JSON to ``path`` atomically."""
    with atomic_write(path) as f:
        json.dump(payload, f, indent=indent)
        f.write("\n")
