"""Cache files derived from a dataset (frozen features, aux frames and their tokens, read-out fits), each with
a record of its content.

A cache is named by a hash of what it is computed from, not of what it holds: a file changed afterwards (features
zeroed, weights scaled) is still well formed, and a run would train on it. So every cache gets, once it is whole,
a record beside it (``<name>.sha256``: size and SHA-256 of its bytes); a run reads a cache only after checking
it, refuses one whose bytes changed, and rebuilds one without a record (written by an older version, or cut off
before its record). A digest proves integrity, not origin: whoever ships a dataset can poison a cache and write
its digest anew. So the record is also signed (HMAC-SHA256) with a key of this user's on this machine
(``$XDG_CONFIG_HOME/dust-rl/cache.key``, default ``~/.config``, created once, mode 0600): a cache whose record
another key signed (a copied or downloaded dataset's) is built again, not read.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import pathlib
import sys
import uuid
from functools import cache

from dust_rl.errors import DatasetError
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.storage.checkpoint_dirs import file_sha256

RECORD_SUFFIX = ".sha256"
# The cache folders, by what they hold, under a dataset's cache root (DemoDataset.cache_root).
CACHE_FOLDERS = {"features": "frozen image features", "aux_frames": "aux frames and their tokens",
                 "readout_cache": "read-out fits"}


def record_path(path: pathlib.Path) -> pathlib.Path:
    return path.with_name(path.name + RECORD_SUFFIX)


@cache
def signing_key() -> bytes:
    """This user's key for cache records (module doc), created on first use; where it cannot be kept, one for this
    process alone (its caches are then rebuilt by every later process)."""
    path = pathlib.Path(os.environ.get("XDG_CONFIG_HOME") or os.path.expanduser("~/.config")) / "dust-rl" / "cache.key"
    try:
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as file:
                file.write(os.urandom(32))
            try:
                os.link(tmp, path)  # never over a key another process made meanwhile
            except FileExistsError:
                pass
            finally:
                tmp.unlink()
        key = path.read_bytes()
        if len(key) >= 32:
            return key
    except OSError:
        pass
    print(f"dust-rl: note: {path} cannot hold the key of cache records; caches are trusted in this process only",
          file=sys.stderr)
    return os.urandom(32)


def _signature(size: int, digest: str) -> str:
    return hmac.new(signing_key(), f"{size}:{digest}".encode(), hashlib.sha256).hexdigest()


def record_cache(path: pathlib.Path) -> None:
    """Write the signed record of the whole cache file ``path``."""
    size, digest = path.stat().st_size, file_sha256(path)
    write_json_atomic(record_path(path), {"size": size, "sha256": digest, "signature": _signature(size, digest)})


def cached(path: pathlib.Path) -> bool:
    """Whether ``path`` holds a cache to read: the file and its record exist, the record was signed here, and the
    file's bytes are the recorded ones; False means build it (again).

    Raises:
        DatasetError: the file's bytes are not those recorded (changed since it was written).
    """
    if not (path.is_file() and record_path(path).is_file()):
        return False
    try:
        record = json.loads(record_path(path).read_text())
        size, digest, signature = int(record["size"]), str(record["sha256"]), str(record.get("signature"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    if not hmac.compare_digest(signature, _signature(size, digest)):
        print(f"dust-rl: note: {path} was cached elsewhere or by an older version (its record is not signed here); "
              "building it again",
              file=sys.stderr)
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
