"""Load memmap TensorDicts only after checking that their files are whole.

``TensorDict.load_memmap`` trusts the files it maps: a truncated ``.memmap`` file
loads silently and reads as zeros (or crashes the process with SIGBUS on access).
Checking every file's size against its recorded shape and dtype first turns such
damage into a :class:`DatasetError` that names the file.
"""

from __future__ import annotations

import json
import math
import pathlib

import torch
from tensordict import TensorDict

from .errors import DatasetError


def check_memmap_dir(path: pathlib.Path) -> None:
    """Raise :class:`DatasetError` if a memmap TensorDict folder is missing, unreadable or truncated."""
    meta_path = path / "meta.json"
    if not meta_path.is_file():
        raise DatasetError(f"{path}: not a memmap TensorDict folder (no meta.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DatasetError(f"{meta_path}: unreadable ({err})") from err
    for key, entry in meta.items():
        if not isinstance(entry, dict):
            continue
        if entry.get("type") == "TensorDict":
            check_memmap_dir(path / key)
        elif "shape" in entry and "dtype" in entry:
            _check_leaf(path / f"{key}.memmap", entry)


def _check_leaf(file: pathlib.Path, entry: dict) -> None:
    if not file.is_file():
        raise DatasetError(f"{file}: missing data file")
    dtype = getattr(torch, entry["dtype"].removeprefix("torch."))
    expected = math.prod(entry["shape"]) * torch.empty((), dtype=dtype).element_size()
    actual = file.stat().st_size
    if actual < expected:
        raise DatasetError(f"{file}: truncated ({actual} bytes, expected {expected})")


def load_memmap_checked(path: pathlib.Path) -> TensorDict:
    """``TensorDict.load_memmap(path)`` after :func:`check_memmap_dir`."""
    check_memmap_dir(path)
    try:
        return TensorDict.load_memmap(path)
    except Exception as err:  # tensordict raises several types for damaged metadata
        raise DatasetError(f"{path}: cannot load memmap TensorDict ({type(err).__name__}: {err})") from err
