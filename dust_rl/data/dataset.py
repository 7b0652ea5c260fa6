"""Read a demonstration dataset: its metadata and its rows as a memmap TensorDict.

Loading checks what a training run would otherwise trip over later: the metadata
format, that every data file is whole, that row counts agree with the episode
table, and (on request) that the dataset fits the env it will be used with.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import pathlib

import gymnasium as gym
import torch
from tensordict import NonTensorStack, TensorDict

from dust_rl.agents.factory import IMAGE_SIZE_INFO, frame_size
from dust_rl.errors import DatasetError
from dust_rl.keys import INSTRUCTION_KEY
from dust_rl.storage.memmap_io import load_memmap_checked

from .layout import META_FILE
from .metadata import SPEC_KEYS, read_meta, recorded_env_spec, spec_mismatches

# Entries of a finished dataset's meta.json that its readers use, with their JSON types.
FINISHED_META = {"env_id": str, "env_kwargs": dict, "spec": dict, "tasks": list, "instructions": list,
                 "episodes": list, "num_rows": int}


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def writable(folder: pathlib.Path) -> bool:
    """Whether this process may create files in ``folder`` (a read-only dataset's caches go elsewhere)."""
    return os.access(folder, os.W_OK | os.X_OK)


def cache_root(root: pathlib.Path, identity: dict, cache_dir: pathlib.Path | None = None) -> pathlib.Path:
    """The folder of the caches derived from the dataset at ``root`` (of version ``identity``).

    ``cache_dir`` if given, else the dataset folder itself when this process may write there, else the user's
    cache folder (``$XDG_CACHE_HOME``, default ``~/.cache``, ``/dust-rl``); outside the dataset, in a subfolder
    named by a digest of the dataset's path and version, so datasets never share caches.
    """
    if cache_dir is None and writable(root):
        return root
    base = cache_dir or pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache") / "dust-rl"
    key = json.dumps({"dataset": str(root.resolve()), **identity}, sort_keys=True)
    return base / hashlib.sha256(key.encode()).hexdigest()[:16]


class DemoDataset:
    """A finalised dataset folder (see :mod:`dust_rl.data.layout`).

    Args:
        root: the folder written by :func:`dust_rl.data.collect_demos` (or ``dataset import``).
        env: if given, raise :class:`DatasetError` unless the dataset's cameras, image shape,
            state/action sizes and control rate match this env's.
        cache_dir: where caches derived from the dataset go (:func:`cache_root`); default: inside it when it
            is writable, else the user's cache folder.

    Attributes:
        meta: the parsed ``meta.json``.
        data: all rows, a memmap TensorDict ``[num_rows]`` (nothing is read until indexed).
    """

    def __init__(self, root: str | pathlib.Path, env: gym.Env | None = None,
                 cache_dir: str | pathlib.Path | None = None) -> None:
        self.root = pathlib.Path(root)
        self.cache_dir = None if cache_dir is None else pathlib.Path(cache_dir)
        self.meta = read_meta(self.root)
        if not self.meta.get("data"):
            raise DatasetError(f"{self.root}: collection was not finished (no consolidated data in {META_FILE}); "
                               "re-run the collect command to resume it")
        self._check_entries()
        self._check_episode_table()
        self.data = load_memmap_checked(self.root / self.meta["data"])
        if self.data.shape[0] != self.meta["num_rows"] or self.meta["num_rows"] != sum(self.lengths.tolist()):
            raise DatasetError(f"{self.root}: {self.data.shape[0]} rows on disk, but {META_FILE} expects "
                               f"{self.meta['num_rows']} (episode lengths sum to {sum(self.lengths.tolist())})")
        if env is not None:
            self.check_env(env)

    def _check_entries(self) -> None:
        """The entries a finished dataset's readers use must be there, of their JSON types."""
        bad = [key for key, kind in FINISHED_META.items() if not isinstance(self.meta.get(key), kind)]
        spec = self.meta.get("spec")
        bad += [f"spec.{key}" for key in SPEC_KEYS if isinstance(spec, dict) and key not in spec]
        if bad:
            raise DatasetError(f"{self.root / META_FILE}: missing or malformed {', '.join(bad)}; the file was edited "
                               "or damaged: restore it, or collect (import) the dataset again")

    def _check_episode_table(self) -> None:
        """Episodes must lie back to back from row 0, each at least one row long, with a known task and
        instruction."""
        row, tasks = 0, self.meta.get("tasks") or []
        for i, episode in enumerate(self.meta.get("episodes") or []):
            episode = episode if isinstance(episode, dict) else {}
            length, start, index = episode.get("length"), episode.get("row_start"), episode.get("instruction_index")
            if not (_is_int(length) and length >= 1 and start == row and _is_int(index)
                    and 0 <= index < len(self.meta.get("instructions", [])) and episode.get("task") in tasks):
                raise DatasetError(f"{self.root / META_FILE}: episode {i} is garbled (length {length!r} at row "
                                   f"{start!r}, expected row {row}; instruction {index!r}; task "
                                   f"{episode.get('task')!r} of {tasks})")
            row += length

    def __len__(self) -> int:
        return self.data.shape[0]

    @functools.cached_property
    def cache_root(self) -> pathlib.Path:
        """Where caches derived from this dataset (features, aux frames, read-out fits) go: see
        :func:`cache_root`."""
        return cache_root(self.root, self.identity, self.cache_dir)

    @property
    def identity(self) -> dict:
        """What names this version of the dataset: its consolidated data folder (renamed at every collection
        or import that changes it), rows and episodes per task. A run checkpoint stores it, so a resume can
        tell that the dataset changed under it."""
        return {"data": self.meta["data"], "num_rows": self.meta["num_rows"],
                "episodes_per_task": self.meta.get("episodes_per_task")}

    @property
    def num_episodes(self) -> int:
        return len(self.meta["episodes"])

    @property
    def tasks(self) -> list[str]:
        return self.meta["tasks"]

    @property
    def instructions(self) -> list[str]:
        return self.meta["instructions"]

    @property
    def cameras(self) -> list[str]:
        return self.meta["spec"]["cameras"]

    @functools.cached_property
    def lengths(self) -> torch.Tensor:
        return torch.tensor([episode["length"] for episode in self.meta["episodes"]], dtype=torch.int64)

    @functools.cached_property
    def episode_starts(self) -> torch.Tensor:
        return torch.tensor([episode["row_start"] for episode in self.meta["episodes"]], dtype=torch.int64)

    @functools.cached_property
    def row_episode_end(self) -> torch.Tensor:
        """Per row, the row index one past its episode's last row (for window boundaries)."""
        return torch.repeat_interleave(self.episode_starts + self.lengths, self.lengths)

    @functools.cached_property
    def row_task_index(self) -> torch.Tensor:
        """Per row, the index of its episode's task in :attr:`tasks`."""
        task_index = {task: i for i, task in enumerate(self.tasks)}
        episode_task = torch.tensor([task_index[episode["task"]] for episode in self.meta["episodes"]])
        return torch.repeat_interleave(episode_task, self.lengths)

    def episode(self, index: int) -> TensorDict:
        """Rows of episode ``index`` (a memmap view) with its instruction attached."""
        start, length = int(self.episode_starts[index]), int(self.lengths[index])
        rows = self.data[start:start + length]
        return self.with_instructions(rows)

    def with_instructions(self, rows: TensorDict) -> TensorDict:
        """``rows`` plus a ``language_instruction`` string per row, from ``instruction_index``."""
        texts = [self.instructions[i] for i in rows.get("instruction_index").reshape(-1).tolist()]
        out = rows.clone(recurse=False)  # a shallow copy: the memmap rows stay read-only
        out.set(INSTRUCTION_KEY, NonTensorStack.from_list(texts) if rows.ndim else texts[0])
        return out

    def check_fits_policy(self, info: dict, policy: object) -> None:
        """Raise :class:`DatasetError` naming each way the dataset is not what the policy (``info``: its record of
        its training, ``policy``: its name) was trained on: its frame size and tasks (a policy at another size, or on
        a task it never saw, would be measured on inputs it was never meant for)."""
        trained, size = info.get(IMAGE_SIZE_INFO), frame_size(self.meta["spec"]["image_shape"])
        problems = []
        if trained and list(trained) != size:
            problems.append(f"frames: {size} px, the policy was trained on {trained}")
        unseen = [task for task in self.tasks if info.get("tasks") and task not in info["tasks"]]
        if unseen:
            problems.append(f"tasks {unseen}, which the policy never trained on (it knows {info['tasks']})")
        if problems:
            raise DatasetError(f"{self.root} does not fit {policy}: " + "; ".join(problems))

    def check_env(self, env: gym.Env) -> None:
        """Raise :class:`DatasetError` naming each way the dataset's arrays do not fit ``env``."""
        problems = spec_mismatches(self.meta["spec"], recorded_env_spec(env))
        if problems:
            raise DatasetError(f"{self.root} does not match the requested env: " + "; ".join(problems))
