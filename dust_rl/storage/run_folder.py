"""A run folder's rules, shared by ``dust-rl train`` and ``dust-rl finetune``.

A new run needs an unused folder; ``--resume`` needs a run there started with the same settings (only
the fields a run may change between sittings, such as threads or progress bars, may differ; a field the
stored run predates counts as its default, so a run started by an older version resumes). ``dust-rl train
--resume`` reads them back (:func:`saved_run_config`) as its defaults, so only a flag given against them is
refused, named with the value given and the run's. The run's
``config.json`` records the full config, the command and package versions, and checkpoints are torchrl
``Checkpoint`` directories kept by a ``CheckpointRotation``. One run writes into a folder at a time: it holds
the folder's lock (:func:`~dust_rl.storage.lock.folder_lock`) from its ``config.json`` to its end. A run resumes
on another device than it was saved on (a GPU run on a CPU-only machine, or the reverse): checkpoints load onto
the CPU and every component copies them onto its own device.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import pathlib
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping

import torch
from torchrl.checkpoint import Checkpoint, CheckpointRotation, GlobalRNGState
from torchrl.checkpoint import CheckpointError as TorchrlCheckpointError

from dust_rl.errors import CheckpointError, ConfigError
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.storage.checkpoint_dirs import check_checkpoint_dir, newest_checkpoint
from dust_rl.storage.config_json import Retired, config_json, flag_path, package_versions, without_retired
from dust_rl.storage.lock import LOCK_FILE, folder_lock


def saved_run_config(out: pathlib.Path, retired: Mapping[str, Retired] | None = None,
                     upgrade: Callable[[dict], dict] | None = None) -> dict:
    """The config the run in ``out`` was started with (its ``config.json``), as JSON values named as this version
    names its settings; ``retired`` and ``upgrade`` as :func:`check_run_folder` takes them.

    Raises:
        FileNotFoundError: no run there.
        ConfigError: an unreadable config, or one with a retired setting at another value.
    """
    saved = out / "config.json"
    if not saved.is_file():
        raise FileNotFoundError(f"{out}: nothing to resume (no config.json); drop --resume to start a run")
    try:
        stored = json.loads(saved.read_text())["config"]
        if not isinstance(stored, dict):
            raise TypeError(f"'config' is {stored!r:.60}, not an object of settings")
    except (ValueError, KeyError, TypeError, RecursionError) as err:  # RecursionError: nested past Python's stack
        raise ConfigError(f"{saved}: unreadable run config ({err!r}); start a new run with another --out") from err
    try:
        stored = without_retired(stored, retired or {})
    except ValueError as err:
        raise ConfigError(f"{out} was started with {err}; it cannot resume: start a new run with another "
                          "--out") from None
    return upgrade(stored) if upgrade is not None else stored


def check_run_folder(config, resumable: Iterable[str], retired: Mapping[str, Retired] | None = None,
                     upgrade: Callable[[dict], dict] | None = None) -> None:
    """Raise unless ``config.out`` suits ``config.resume`` (a dataclass with ``out`` and ``resume``); ``retired``:
    settings earlier versions stored, at the one value this version honours and the commit that runs the others
    (:func:`~dust_rl.storage.config_json.without_retired`); ``upgrade``: the stored config as this version names its
    settings (those an earlier version stored under other names moved to theirs). Settings are compared one by one,
    those of nested configs by their dotted names (``resumable`` names them so: ``runtime.threads``).

    Raises:
        FileNotFoundError: ``resume`` without a run there.
        FileExistsError: a new run in a folder that holds one.
        ConfigError: ``resume`` with settings other than the stored run's (fields not in ``resumable``; the message
            names each one's flag, the value given and the run's), or of a run stored with a retired setting at
            another value.
    """
    if config.resume:
        stored = saved_run_config(config.out, retired, upgrade)
        resumable = set(resumable)
        defaults = _defaults(config)
        given = {k: v for k, v in _dotted(config, config_json(config)).items() if k not in resumable}
        saved = {k: _at(stored, k, _at(defaults, k, None)) for k in given}
        changed = [k for k in given if saved[k] != given[k]]
        if changed:
            flags = "; ".join(f"{_flag(k, given[k])} given, the run's is {_shown(saved[k])}" for k in changed)
            raise ConfigError(f"{config.out} was started with other settings ({', '.join(changed)}): {flags}; resume "
                              "without those flags (or with the run's values) or use a new --out")
    elif any((config.out / "checkpoints").glob("*")):
        raise FileExistsError(f"{config.out} already holds a run; pass --resume to continue it or choose another --out")
    elif (config.out / "config.json").exists():
        raise FileExistsError(f"{config.out} holds a run stopped before its first checkpoint; pass --resume to start "
                              "it again with its own settings, delete the folder to start another there, or choose "
                              "another --out")


def _flag(name: str, value: object) -> str:
    """The command-line flag that gives the dotted setting ``name`` the JSON ``value`` (``--optim.steps 20``,
    ``--runtime.no-progress``)."""
    group, dot, field = flag_path(name).rpartition(".")
    if isinstance(value, bool):
        return f"--{group}{dot}{'' if value else 'no-'}{field}"
    return f"--{group}{dot}{field} {_shown(value)}"


def _shown(value: object) -> str:
    """A JSON value as a command line gives it (a list as its items)."""
    return " ".join(map(str, value)) if isinstance(value, list) else str(value)


def _defaults(config) -> dict:
    """The JSON values of ``config``'s fields that have defaults, at those defaults."""
    values = {}
    for field in dataclasses.fields(config):
        if field.default is not dataclasses.MISSING:
            value = field.default
        elif field.default_factory is not dataclasses.MISSING:
            value = field.default_factory()
        else:
            continue
        values[field.name] = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
    return json.loads(json.dumps(values, default=str))


def _dotted(config, values: dict) -> dict:
    """``values`` (``config`` as JSON values) by dotted name, the fields of nested dataclasses one by one."""
    dotted = {}
    for field in dataclasses.fields(config):
        nested = getattr(config, field.name)
        if dataclasses.is_dataclass(nested):
            dotted |= {f"{field.name}.{k}": v for k, v in _dotted(nested, values[field.name]).items()}
        else:
            dotted[field.name] = values[field.name]
    return dotted


def _at(values: Mapping, dotted: str, missing: object) -> object:
    """The value at the ``dotted`` name in nested ``values``; ``missing`` where there is none."""
    for name in dotted.split("."):
        if not isinstance(values, Mapping) or name not in values:
            return missing
        values = values[name]
    return values


@contextlib.contextmanager
def locked_run_folder(config, resumable: Iterable[str], command: str | None,
                      retired: Mapping[str, Retired] | None = None,
                      upgrade: Callable[[dict], dict] | None = None) -> Iterator[None]:
    """Hold ``config.out``'s lock for the ``with`` body, a new run's ``config.json`` written first.

    Two runs in one folder would interleave their logs and checkpoints. The folder is checked again under
    the lock (another run may have started since :func:`check_run_folder`); a new run refused there leaves
    no folder behind.

    Raises:
        FolderLockedError: another process holds the folder (the message names its pid).
        FileExistsError, FileNotFoundError, ConfigError: as :func:`check_run_folder` (``retired`` and ``upgrade``
            too).
    """
    created = not config.out.exists()
    config.out.mkdir(parents=True, exist_ok=True)
    with folder_lock(config.out):
        try:
            check_run_folder(config, resumable, retired, upgrade)
            if not config.resume:
                write_run_config(config, command)
        except BaseException:
            if created:
                (config.out / LOCK_FILE).unlink(missing_ok=True)
                config.out.rmdir()
            raise
        yield


def write_run_config(config, command: str | None) -> None:
    """``config.json`` of a new run: the full config, the command and package versions."""
    config.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(config.out / "config.json",
                      {"config": config_json(config), "command": command, "versions": package_versions()}, indent=2)


# The accelerator generators torchrl's GlobalRNGState saves, by their key, with the test of their presence here.
_ACCELERATOR_RNGS: dict[str, Callable[[], bool]] = {
    "torch_cuda": torch.cuda.is_available,
    "torch_xpu": lambda: hasattr(torch, "xpu") and torch.xpu.is_available(),
    "torch_mps": torch.backends.mps.is_available,
}


class RunRNGState(GlobalRNGState):
    """torchrl's process-global RNG state, which also restores where an accelerator it saved is absent.

    torchrl refuses a saved CUDA generator on a machine without CUDA, so a GPU run could not resume on a CPU.
    Its Python, NumPy and CPU torch generators resume as saved; the absent accelerator's state has nothing to
    seed, and the run is no longer the GPU run's bit for bit (which a change of device never is).
    """

    def load_state_dict(self, state_dict: Mapping[str, object]) -> None:
        absent = [key for key, present in _ACCELERATOR_RNGS.items() if key in state_dict and not present()]
        if absent:
            warnings.warn(f"resuming without the saved {', '.join(absent)} random state: that device is absent "
                          "here, so the run continues, no longer bit for bit", stacklevel=2)
        super().load_state_dict({key: value for key, value in state_dict.items() if key not in absent})


def restore(checkpoint: Checkpoint, rotation: CheckpointRotation) -> dict:
    """Load the newest checkpoint (if any) into the run's objects; returns its metadata (``step`` and whatever
    the run saved with it; empty: no checkpoint).

    Raises:
        CheckpointError: the newest checkpoint is damaged, holds files this package does not write (which could
            run code when loaded; nothing is loaded then) or does not load into these objects.
    """
    try:
        latest = newest_checkpoint(rotation)
        if latest is None:
            return {}
        check_checkpoint_dir(latest)
    except CheckpointError as err:
        raise CheckpointError(f"cannot resume from this checkpoint ({err})") from err
    try:
        checkpoint.load(latest, map_location="cpu")
    except (TorchrlCheckpointError, KeyError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{latest}: cannot resume from this checkpoint ({err})") from err
    return dict(Checkpoint.manifest(latest)["metadata"])
