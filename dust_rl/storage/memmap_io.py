"""Load memmap TensorDicts only after checking that they hold nothing but whole tensors.

``TensorDict.load_memmap`` trusts the folder it maps. A ``meta.json`` may name any
registered class, and a ``NonTensorData`` entry or a tensorclass brings an
``other.pickle`` that tensordict 0.14 unpickles by default, which runs code from
the dataset; a truncated ``.memmap`` file loads silently and reads as zeros (or
crashes the process with SIGBUS on access). Datasets are downloaded and shared,
so every ``meta.json`` is checked against a whitelist of what this package writes
(plain ``TensorDict`` folders of tensors with the dtypes below, on a device named as torch names one: a
checkpoint written on a GPU records ``cuda:0``), every file
must lie inside the folder (no symlink out) and hold its recorded size, and only
then is the folder loaded, with ``allow_pickle=False`` besides. Anything else is
a :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import json
import math
import pathlib
import re

import torch
from tensordict import TensorDict

from dust_rl.errors import DatasetError
from dust_rl.storage.paths import SAFE_NAME, inside

_TENSORDICT = str(TensorDict)  # the "_type" tensordict records for a plain TensorDict
_SUBFOLDER = {"type": "TensorDict"}
_DTYPES = {str(dtype): dtype for dtype in (torch.uint8, torch.bool, torch.int32, torch.int64, torch.float32,
                                            torch.float64)}
_HEADER_KEYS = ("_type", "shape", "device")
_LEAF_KEYS = {"shape", "dtype", "device", "is_nested"}
_DEVICE = re.compile(r"(cpu|cuda|mps|xpu)(:[0-9]+)?")


def _is_device(value: object) -> bool:
    """None (tensordict's "wherever"), or a device name such as ``cpu`` or ``cuda:0``."""
    return value in (None, "None") or (isinstance(value, str) and _DEVICE.fullmatch(value) is not None)


def check_memmap_dir(path: pathlib.Path, root: pathlib.Path | None = None) -> None:
    """Raise :class:`DatasetError` unless ``path`` is a whole memmap TensorDict folder of tensors only.

    Args:
        path: the folder.
        root: the folder that every file must stay inside (default: ``path``).
    """
    root = path if root is None else root
    meta_path = path / "meta.json"
    if not meta_path.is_file():
        raise DatasetError(f"{path}: not a memmap TensorDict folder (no meta.json)")
    inside(root, str(meta_path.relative_to(root)), meta_path)
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"{meta_path}: unreadable ({err})") from err
    if not isinstance(meta, dict) or meta.get("_type") != _TENSORDICT:
        found = meta.get("_type") if isinstance(meta, dict) else type(meta).__name__
        raise DatasetError(f"{meta_path}: holds {found!r}, not a TensorDict of tensors; refusing to load it "
                           "(non-tensor entries are pickles, which would run code on load)")
    if not _is_shape(meta.get("shape")) or not _is_device(meta.get("device")):
        raise DatasetError(f"{meta_path}: bad batch shape {meta.get('shape')!r} or device {meta.get('device')!r}")
    for key, entry in meta.items():
        if key in _HEADER_KEYS:
            continue
        if not SAFE_NAME.fullmatch(key):
            raise DatasetError(f"{meta_path}: entry name {key!r} is not one this package writes; refused")
        if entry == _SUBFOLDER:
            check_memmap_dir(path / key, root)
        elif isinstance(entry, dict) and "type" not in entry:
            _check_leaf(path / f"{key}.memmap", entry, root, meta_path)
        else:
            found = entry.get("type") if isinstance(entry, dict) else entry
            raise DatasetError(f"{meta_path}: entry {key!r} is {found!r}, not a tensor; refusing to load it "
                               "(non-tensor entries are pickles, which would run code on load)")


def _is_shape(value: object) -> bool:
    return isinstance(value, list) and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in value)


def _check_leaf(file: pathlib.Path, entry: dict, root: pathlib.Path, meta_path: pathlib.Path) -> None:
    if (not set(entry) <= _LEAF_KEYS or entry.get("dtype") not in _DTYPES or not _is_shape(entry.get("shape"))
            or entry.get("is_nested", False) is not False or not _is_device(entry.get("device"))):
        raise DatasetError(f"{meta_path}: entry {file.stem!r} is not a plain tensor of a known dtype: {entry}")
    expected = math.prod(entry["shape"]) * _DTYPES[entry["dtype"]].itemsize
    if not file.is_file():
        if expected:  # tensordict writes no file for an empty tensor
            raise DatasetError(f"{file}: missing data file")
        return
    inside(root, str(file.relative_to(root)), meta_path)
    actual = file.stat().st_size
    if actual < expected:
        raise DatasetError(f"{file}: truncated ({actual} bytes, expected {expected})")


def load_memmap_checked(path: pathlib.Path) -> TensorDict:
    """``TensorDict.load_memmap(path)`` after :func:`check_memmap_dir`, never unpickling."""
    check_memmap_dir(path)
    try:
        return TensorDict.load_memmap(path, allow_pickle=False)
    except Exception as err:  # tensordict raises several types for damaged metadata
        raise DatasetError(f"{path}: cannot load memmap TensorDict ({type(err).__name__}: {err})") from err
