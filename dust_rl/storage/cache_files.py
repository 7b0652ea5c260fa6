"""Cache files derived from a dataset (frozen features, aux frames and their tokens, read-out fits), each with
a record of its content.

A cache is named by a hash of what it is computed from, not of what it holds: a file changed afterwards (features
zeroed, weights scaled) is still well formed, and a run would train on it. So every cache gets, once it is whole,
a record beside it (``<name>.sha256``: size and SHA-256 of its bytes); a run reads a cache only after checking
it, refuses one whose bytes changed, and rebuilds one without a record (written by an older version, or cut off
before its record).
"""

from __future__ import annotations

import json
import pathlib

from dust_rl.errors import DatasetError
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.storage.checkpoint_dirs import file_sha256

RECORD_SUFFIX = ".sha256"
# The cache folders, by what they hold, under a dataset's cache root (DemoDataset.cache_root).
CACHE_FOLDERS = {"features": "frozen image features", "aux_frames": "aux frames and their tokens",
                 "readout_cache": "read-out fits"}


def record_path(path: pathlib.Path) -> pathlib.Path:
    return path.with_name(path.name + RECORD_SUFFIX)


def record_cache(path: pathlib.Path) -> None:
    """Write the record of the whole cache file ``path``."""
    write_json_atomic(record_path(path), {"size": path.stat().st_size, "sha256": file_sha256(path)})


def cached(path: pathlib.Path) -> bool:
    """Whether ``path`` holds a cache to read: the file and its record exist, and its bytes are the recorded
    ones; False means build it (again).

    Raises:
        DatasetError: the file's bytes are not those recorded (changed since it was written).
    """
    if not (path.is_file() and record_path(path).is_file()):
        return False
    try:
        record = json.loads(record_path(path).read_text())
        size, digest = int(record["size"]), str(record["sha256"])
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if path.stat().st_size != size or file_sha256(path) != digest:
        raise DatasetError(f"{path}: this cache changed since it was written (its bytes are not the recorded "
                           f"ones); delete it and its {RECORD_SUFFIX} file to rebuild it")
    return True


def cache_files(root: pathlib.Path) -> list[tuple[pathlib.Path, int]]:
    """The cache files under a dataset's cache root, with their sizes in bytes (records left out)."""
    return [(path, path.stat().st_size) for folder in CACHE_FOLDERS
            for path in sorted((root / folder).rglob("*") if (root / folder).is_dir() else ())
            if path.is_file() and path.suffix != RECORD_SUFFIX and not path.name.startswith(".")]
