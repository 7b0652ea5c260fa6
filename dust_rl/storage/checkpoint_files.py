"""Atomic checkpoints with a kind tag and a format version: one file, or a folder without pickle.

A policy or encoder checkpoint file is one ``torch.save`` file holding only
tensors, numbers, strings, lists and dicts, so it loads with
``weights_only=True`` (no code runs on load). It is written through
:func:`~dust_rl.storage.atomic_files.atomic_write`: a killed writer leaves the
old file or the new one, never half of one.

A checkpoint folder follows the Hugging Face / LeRobot convention:
``config.json`` (everything that is not a tensor, with the kind and version)
and ``model.safetensors`` (the tensors), so reading it parses JSON and raw
tensor bytes only. It is written to a temp folder beside the target, fsynced,
and renamed into place; an old folder is first renamed aside, then removed.
A killed writer leaves no half folder at the target: the old folder or the new
one (killed between the two renames, the old one is kept beside it under a
hidden name). An existing folder is replaced only if it holds a checkpoint of
the same kind or nothing, so a mistyped path never deletes data.

Why in storage: policy, encoder and RL agent files and read-out caches are all
read and written here (with the checks that loaded tensors hold usable values),
and none of it knows a model; each loader above says what its payload holds.
The agents import this module, never the reverse.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import shutil
import uuid
from collections.abc import Collection, Mapping

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor

from dust_rl.errors import CheckpointError, one_line
from dust_rl.storage.atomic_files import atomic_write

FORMAT_VERSION = 1
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
MAX_CONFIG_BYTES = 16 * 2**20  # a policy's config.json is a few kB; an encoder's transformers config tens of kB


def save_checkpoint(payload: dict, path: str | pathlib.Path, kind: str) -> pathlib.Path:
    """Write ``payload`` tagged with ``kind`` atomically to ``path``; returns the path.

    Raises:
        CheckpointError: ``path`` exists and is not a checkpoint file of ``kind`` (an encoder saved over a trained
            policy would lose it).
    """
    path = pathlib.Path(path)
    check_replaceable_file(path, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        torch.save({"kind": kind, "format_version": FORMAT_VERSION, **payload}, f)
    return path


def check_replaceable_file(path: pathlib.Path, kind: str) -> None:
    """Raise :class:`CheckpointError` unless ``path`` is free or a checkpoint file of ``kind`` (what saving one
    may replace); a command checks its target with it before it works for the file."""
    if (path.exists() or path.is_symlink()) and not (path.is_file() and checkpoint_kind(path) == kind):
        raise CheckpointError(f"{path} exists and is not a {kind!r} checkpoint file; remove it or choose another path")


def load_checkpoint(path: str | pathlib.Path, kind: str) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`, checking its kind and version.

    Raises:
        CheckpointError: the file is missing, corrupt, of another kind or another format version.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: not a regular file (a FIFO, device or socket); give a checkpoint file or folder"
                              if path.exists() else f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"{path}: corrupt or not a torch checkpoint ({one_line(err)})") from err
    return _checked(payload, kind, path)


def checkpoint_kind(path: str | pathlib.Path) -> str | None:
    """The kind a checkpoint file is tagged with, read without loading its tensors (memory-mapped); None for a
    folder or anything that is not a readable checkpoint file (its loader then says what is wrong); a FIFO or device is
    never opened (reading one would block or never end)."""
    if not pathlib.Path(path).is_file():
        return None
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # a folder, a missing, truncated or foreign file: for the loader to report
        return None
    kind = payload.get("kind") if isinstance(payload, dict) else None
    return kind if isinstance(kind, str) else None


def save_folder(config: dict, tensors: dict[str, Tensor], path: str | pathlib.Path, kind: str) -> pathlib.Path:
    """Write ``config`` (JSON-able) tagged with ``kind`` and ``tensors`` to the folder ``path``, atomically.

    Raises:
        CheckpointError: ``path`` exists and is not an empty folder or a checkpoint folder of ``kind``.
        TypeError: ``config`` holds something JSON cannot (nothing is written then).
    """
    path = pathlib.Path(path)
    text = json.dumps({"kind": kind, "format_version": FORMAT_VERSION, **config}, indent=1) + "\n"
    if path.exists() or path.is_symlink():
        _check_replaceable(path, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp, old = (path.with_name(f".{path.name}.{uuid.uuid4().hex}.{end}") for end in ("tmp", "old"))
    try:
        tmp.mkdir()
        (tmp / CONFIG_FILE).write_text(text)
        save_file({name: t.detach().cpu().clone(memory_format=torch.contiguous_format) for name, t in tensors.items()},
                  tmp / WEIGHTS_FILE)
        os.chmod(tmp / WEIGHTS_FILE, (tmp / CONFIG_FILE).stat().st_mode & 0o777)  # safetensors' own is 0600
        for name in (CONFIG_FILE, WEIGHTS_FILE, "."):
            _fsync(tmp / name)
        if path.exists():
            os.rename(path, old)
            try:
                os.rename(tmp, path)
            except OSError:
                os.rename(old, path)  # the old folder goes back; nothing is lost
                raise
            shutil.rmtree(old)
        else:
            os.rename(tmp, path)
        _fsync(path.parent)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def _fsync(path: pathlib.Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _check_replaceable(path: pathlib.Path, kind: str) -> None:
    """Raise unless ``path`` is an empty folder or a checkpoint folder of ``kind`` (what saving may replace)."""
    if path.is_dir() and not path.is_symlink():
        if not any(path.iterdir()):
            return
        with contextlib.suppress(CheckpointError):
            _read_config(path, kind)
            return
    raise CheckpointError(f"{path} exists and is not a {kind!r} checkpoint folder; remove it or choose another path")


def load_folder(path: str | pathlib.Path, kind: str) -> tuple[dict, dict[str, Tensor]]:
    """Read a folder written by :func:`save_folder`: its config (with kind and version checked) and its tensors.

    Raises:
        CheckpointError: a file is missing, a symlink leading out of the folder, too large, not JSON (an object)
            or not safetensors, or the config is of another kind or format version.
    """
    path = pathlib.Path(path)
    config = _read_config(path, kind)
    try:
        tensors = load_file(_inside(path, WEIGHTS_FILE))
    except (SafetensorError, OSError) as err:
        raise CheckpointError(f"{path / WEIGHTS_FILE}: corrupt or not safetensors ({one_line(err)})") from err
    return config, tensors


def _inside(folder: pathlib.Path, name: str) -> pathlib.Path:
    """``folder / name``, checked to be a file that stays inside ``folder`` once links are followed."""
    file = folder / name
    if not file.is_file():
        raise CheckpointError(f"{file}: missing; a checkpoint folder holds {CONFIG_FILE} and {WEIGHTS_FILE}")
    if not file.resolve().is_relative_to(folder.resolve()):
        raise CheckpointError(f"{file}: links to {file.resolve()}, outside the checkpoint folder")
    return file


def _read_config(path: pathlib.Path, kind: str) -> dict:
    file = _inside(path, CONFIG_FILE)
    size = file.stat().st_size
    if size > MAX_CONFIG_BYTES:
        raise CheckpointError(f"{file}: {size} bytes, over the {MAX_CONFIG_BYTES} a checkpoint config may have")
    try:
        config = json.loads(file.read_bytes())
    except (ValueError, RecursionError, OSError) as err:  # RecursionError: nested deeper than Python's stack
        raise CheckpointError(f"{file}: not JSON ({one_line(err)})") from err
    return _checked(config, kind, file)


def _checked(payload: object, kind: str, source: pathlib.Path) -> dict:
    """``payload`` if it is a dict tagged with ``kind`` and this format version (files and folders alike)."""
    if not isinstance(payload, dict) or payload.get("kind") != kind:
        found = payload.get("kind") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{source}: expected a {kind!r} checkpoint, found {found!r}")
    if payload.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{source}: format version {payload.get('format_version')!r}; "
                              f"this dust-rl reads version {FORMAT_VERSION}")
    return payload


def non_finite(tensors: Mapping[str, object], unbounded: Collection[str] = ()) -> list[str]:
    """The names of the floating-point tensors among ``tensors`` that hold NaN or infinity (only NaN for the names in
    ``unbounded``, where infinity means no bound)."""
    def bad(name: str, t: Tensor) -> bool:
        return bool(t.isnan().any() if name in unbounded else ~torch.isfinite(t).all())

    return sorted(name for name, t in tensors.items()
                  if isinstance(t, Tensor) and t.is_floating_point() and bad(name, t))


def check_tensor_values(tensors: Mapping[str, object], into: Mapping[str, Tensor],
                        unbounded: Collection[str] = ()) -> None:
    """Raise ``ValueError`` naming the ``tensors`` that would poison the module they load into (``into``: its
    tensors, by the same names): integers where it holds floats, and NaN or infinity (``unbounded``: names that
    may be infinite, as :func:`non_finite` takes them).

    Why: either loads without a complaint (an integer tensor is cast into weights nothing trained) and makes every
    action NaN, first noticed deep inside an env step; checked where the file is read, the error names it.
    """
    integers = sorted(name for name, t in tensors.items() if isinstance(t, Tensor) and name in into
                      and into[name].is_floating_point() and not t.is_floating_point())
    nan = non_finite(tensors, unbounded)
    problems = ([f"integer values where the model holds floats in {_few(integers)}"] if integers else []) + (
        [f"NaN or infinity in {_few(nan)}"] if nan else [])
    if problems:
        raise ValueError(f"{'; '.join(problems)} (the file was damaged, or saved from a run that diverged)")


def _few(names: list[str], shown: int = 4) -> str:
    """``names`` in a message: the first ``shown`` and how many more."""
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return f"{names[:shown]}{more}"

