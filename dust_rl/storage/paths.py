"""Paths read from a file (dataset metadata, checkpoint records) stay inside their folder.

Datasets and run folders are downloaded and shared, so a path written in them is untrusted.
"""

from __future__ import annotations

import pathlib
import re

from dust_rl.errors import DatasetError

# A name the package writes for an entry or folder: no separators, never "." or "..".
SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


def inside(root: pathlib.Path, relative: object, source: object) -> pathlib.Path:
    """``root / relative``, for a path read from a file: refused unless it stays inside ``root``.

    Datasets are downloaded and shared, so a path in their metadata is untrusted: an absolute
    path, a ``..`` step or a symlink out of the folder would read (or, for a writer, delete)
    files elsewhere.

    Args:
        root: the folder the path must stay in.
        relative: the path as read (anything but a relative ``str`` is refused).
        source: the file that named it, for the message.

    Raises:
        DatasetError: naming ``source`` and the path.
    """
    if not isinstance(relative, str) or not relative:
        raise DatasetError(f"{source}: expected a relative path inside {root}, got {relative!r}")
    path = pathlib.PurePosixPath(relative)
    if path.is_absolute() or "\\" in relative or ".." in path.parts:
        raise DatasetError(f"{source}: path {relative!r} leaves the dataset folder {root}; refused")
    target = root / relative
    try:
        escapes = not target.resolve().is_relative_to(root.resolve())
    except (OSError, RuntimeError) as err:  # a symlink loop
        raise DatasetError(f"{source}: path {relative!r} does not resolve ({err})") from err
    if escapes:
        raise DatasetError(f"{source}: path {relative!r} is a symlink out of the dataset folder {root}; refused")
    return target
