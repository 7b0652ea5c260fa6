"""A run's torchrl checkpoint folders: written with a digest of every file, read back only once checked.

torchrl's ``Checkpoint`` stores each component as a memmap TensorDict folder (``state/``) beside a JSON
schema (``state.json``) and reads it back with ``tensordict.load``, which unpickles non-tensor entries:
a checkpoint folder can carry code just as a dataset can. A truncated tensor file, on the other hand,
loads as zeros. So :func:`save_checkpoint_dir` records the size and SHA-256 of every file in
``digests.json`` before the folder gets its final name, and :func:`check_checkpoint_dir` refuses, before
anything is loaded, a folder that is a link or an archive, holds a file or link this package does not
write, whose files differ from the record, whose manifest points elsewhere, or whose memmap folders fail
the dataset whitelist (:func:`~dust_rl.storage.memmap_io.check_memmap_dir`). torchrl writes the tensors
through memory maps, and a memory-mapped write to a full disk kills the process with SIGBUS: the space a
checkpoint takes is reserved first (:func:`reserve_space`), so a full disk ends in ``OSError`` (ENOSPC), which
the commands report in one line (:func:`run_out_of_space`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pathlib
import re
import shutil
import uuid
from collections.abc import Mapping

import numpy as np
import torch
from torchrl.checkpoint import Checkpoint, CheckpointRotation
from torchrl.checkpoint import CheckpointError as TorchrlCheckpointError

from dust_rl.errors import CheckpointError, DatasetError, no_space_left
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.storage.disk_space import reserve_space
from dust_rl.storage.memmap_io import check_memmap_dir

DIGESTS = "digests.json"
_NAME = r"[A-Za-z0-9_.-]+"
# What torchrl's state-dict and JSON adapters write for the components of a run, and nothing else.
_WRITTEN = re.compile(rf"manifest\.json|{re.escape(DIGESTS)}|components/{_NAME}/(state\.json|value\.json|"
                      rf"state/({_NAME}/)*(meta\.json|{_NAME}\.memmap))")
_COMPONENT = re.compile(rf"components/{_NAME}")


def file_sha256(path: pathlib.Path) -> str:
    """SHA-256 of a file's bytes, read in blocks (checkpoints can be large)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def save_checkpoint_dir(checkpoint: Checkpoint, rotation: CheckpointRotation, step: int,
                        metadata: Mapping[str, object]) -> pathlib.Path:
    """``rotation.save(checkpoint, step=step, metadata=metadata)`` with ``digests.json`` inside the folder.

    The folder is staged under a hidden name, gets its digests, and only then takes the name the rotation
    looks for, so a killed writer never leaves a checkpoint without its record.
    """
    rotation.directory.mkdir(parents=True, exist_ok=True)
    for leftover in rotation.directory.glob(f".{rotation.prefix}-*.stage"):  # a killed writer's (the run holds
        shutil.rmtree(leftover, ignore_errors=True)                          # the folder's lock)
    reserve_space(rotation.directory, 2 * state_bytes(checkpoint.components) + (1 << 20))
    final = rotation.directory / f"{rotation.prefix}-{step:012d}"  # torchrl's name for a directory checkpoint
    stage = final.with_name(f".{final.name}.{uuid.uuid4().hex}.stage")
    old = final.with_name(f".{final.name}.{uuid.uuid4().hex}.old")
    try:
        checkpoint.save(stage, format="directory", metadata=metadata)
        files = sorted(p for p in stage.rglob("*") if p.is_file())
        write_json_atomic(stage / DIGESTS, {"files": {p.relative_to(stage).as_posix(): {
            "size": p.stat().st_size, "sha256": file_sha256(p)} for p in files}})
        if final.exists():
            os.replace(final, old)
        os.replace(stage, final)
    finally:
        for leftover in (stage, old):
            shutil.rmtree(leftover, ignore_errors=True)
    rotation.prune()
    return final


def state_bytes(value: object) -> int:
    """Bytes of the tensors and arrays in ``value`` (a component, its ``state_dict``, nested dicts and lists): what
    a checkpoint of it writes, give or take its JSON."""
    if hasattr(value, "state_dict"):
        value = value.state_dict()
    if isinstance(value, torch.Tensor | np.ndarray):
        return value.nbytes
    if isinstance(value, Mapping):
        return sum(state_bytes(v) for v in value.values())
    if isinstance(value, list | tuple):
        return sum(state_bytes(v) for v in value)
    return 0


def run_out_of_space(doing: str) -> contextlib.AbstractContextManager[None]:
    """A full disk while a run (``doing``: "training into <out>") writes, as one line saying what to do."""
    return no_space_left(doing, "free some space and run again (with --resume once a checkpoint exists): "
                         "checkpoints are only ever replaced whole")


def newest_checkpoint(rotation: CheckpointRotation) -> pathlib.Path | None:
    """``rotation.latest()``, refusing a newer folder that torchrl does not recognise as a checkpoint.

    torchrl skips a folder whose ``manifest.json`` is missing or invalid, so a damaged newest checkpoint
    would silently resume an older one, or start the run over.

    Raises:
        CheckpointError: naming that folder.
    """
    latest = rotation.latest()
    pattern = re.compile(rf"{re.escape(rotation.prefix)}-([0-9]+)(\.torchrl)?")
    steps = {entry: int(match[1]) for entry in (rotation.directory.iterdir() if rotation.directory.is_dir() else ())
             if (match := pattern.fullmatch(entry.name))}
    if steps and (latest is None or max(steps.values()) > steps.get(latest, -1)):
        newest = max(steps, key=steps.__getitem__)
        raise CheckpointError(f"{newest}: not a readable checkpoint (its manifest.json is missing or invalid); "
                              "refused")
    return latest


def check_checkpoint_dir(path: pathlib.Path) -> None:
    """Raise :class:`CheckpointError` (one line, naming the file) unless ``path`` is a whole checkpoint folder
    written by :func:`save_checkpoint_dir` that loads without unpickling anything."""
    if path.is_symlink() or not path.is_dir():
        raise CheckpointError(f"{path}: not a checkpoint folder (a link or an archive); refused")
    found = {}
    for folder, dirs, names in os.walk(path):
        for name in dirs + names:
            file = pathlib.Path(folder) / name
            relative = file.relative_to(path).as_posix()
            if file.is_symlink():
                raise CheckpointError(f"{file}: a symlink inside a checkpoint; refused")
            if name in names:
                if not _WRITTEN.fullmatch(relative):
                    raise CheckpointError(f"{file}: not a file this package writes into a checkpoint; refused "
                                          "(it could hold a pickle, which would run code)")
                found[relative] = file
    _check_digests(path, found)
    try:
        manifest = Checkpoint.manifest(path)
    except (TorchrlCheckpointError, OSError, ValueError) as err:
        raise CheckpointError(f"{path / 'manifest.json'}: unreadable ({err})") from err
    for name, record in manifest["components"].items():
        where = record.get("path")
        if not isinstance(where, str) or not _COMPONENT.fullmatch(where) or not (path / where).is_dir():
            raise CheckpointError(f"{path / 'manifest.json'}: component {name!r} at {where!r}, "
                                  "not a folder of this checkpoint; refused")
        if (path / where / "state").is_dir():
            try:
                check_memmap_dir(path / where / "state", path)
            except DatasetError as err:
                raise CheckpointError(str(err)) from err


def _check_digests(path: pathlib.Path, found: dict[str, pathlib.Path]) -> None:
    """Every file of ``found`` (relative name -> path) is in ``digests.json`` with its size and SHA-256."""
    record_path = path / DIGESTS
    if DIGESTS not in found:
        raise CheckpointError(f"{record_path}: missing, so the checkpoint cannot be checked for damage; "
                              "resume from another run folder or start a new run")
    try:
        recorded = json.loads(record_path.read_text())["files"]
        if not isinstance(recorded, dict):
            raise TypeError(f"'files' is a {type(recorded).__name__}")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"{record_path}: unreadable ({err})") from err
    names = set(found) - {DIGESTS}
    if names != set(recorded):
        odd = sorted(names ^ set(recorded))[0]
        state = "missing" if odd in recorded else "not recorded in digests.json"
        raise CheckpointError(f"{path / odd}: {state}; the checkpoint is damaged")
    for name, entry in sorted(recorded.items()):
        file = found[name]
        size = file.stat().st_size
        if not isinstance(entry, dict) or size != entry.get("size"):
            expected = entry.get("size") if isinstance(entry, dict) else entry
            raise CheckpointError(f"{file}: truncated or damaged ({size} bytes, saved with {expected})")
        if file_sha256(file) != entry.get("sha256"):
            raise CheckpointError(f"{file}: damaged (its SHA-256 differs from the one saved with it)")
