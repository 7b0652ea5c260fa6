"""One finished episode on disk: a record (episode.json) and, when kept, its rows.

Collection writes each episode the moment it finishes, atomically (staging
folder + ``os.replace``), so an interrupted collection keeps every finished
episode and resuming only runs the seeds that have no record yet.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

import torch
from tensordict import TensorDict, TensorDictBase

from dust_rl.envs.instruction_space import decode_instruction
from dust_rl.errors import DatasetError
from dust_rl.keys import EXPERT_ACTION_KEY, INSTRUCTION_BYTES_KEY, SEED_KEY, STEP_KEY, SUCCESS_KEY
from dust_rl.storage.disk_space import reserve_space
from dust_rl.storage.memmap_io import load_memmap_checked
from dust_rl.storage.paths import inside

from .layout import (
    EPISODE_FILE,
    EPISODE_TD_DIR,
    EPISODES_DIR,
    episode_dir,
    read_json,
    staging_dir,
    write_json_atomic,
)

# Per-row entries kept from a collected trajectory; the next observation is not stored
# (it is the next row's observation), which halves the image storage.
_NEXT_FLAGS = ("reward", "done", "terminated", "truncated")


@dataclasses.dataclass(frozen=True)
class EpisodeRecord:
    """What is known about one finished episode; the row data lives beside it when `kept`."""

    task: str
    seed: int
    success: bool
    length: int
    instruction: str
    kept: bool

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def trajectory_to_episode(trajectory: TensorDictBase, task: str) -> tuple[TensorDict, EpisodeRecord]:
    """Split one collected trajectory ``[T]`` into stored rows and a record.

    Rows keep the observation at ``t``, the executed ``action``, the label
    ``expert_action``, the step's reward/done flags and success (under ``next``) and
    ``frame_index``. Raises ``RuntimeError`` if the trajectory is not one whole episode.
    """
    length = trajectory.shape[0]
    seeds = trajectory.get(SEED_KEY).reshape(length)
    steps = trajectory.get(STEP_KEY).reshape(length)
    done = trajectory.get(("next", "done")).reshape(length)
    if (seeds != seeds[0]).any() or not torch.equal(steps, torch.arange(length)) or not done[-1] or done[:-1].any():
        raise RuntimeError(f"collector returned a trajectory that is not one whole episode (seeds {seeds.unique()})")
    rows = TensorDict({
        "observation": trajectory.get("observation"),
        "action": trajectory.get("action"),
        EXPERT_ACTION_KEY: trajectory.get(EXPERT_ACTION_KEY),
        "frame_index": steps.long(),
        "next": {**{flag: trajectory.get(("next", flag)) for flag in _NEXT_FLAGS},
                 "success": trajectory.get(("next", SUCCESS_KEY)).bool()},
    }, batch_size=[length])
    instruction = decode_instruction(trajectory.get(INSTRUCTION_BYTES_KEY)[0])
    success = bool(rows.get(("next", "success"))[-1])
    record = EpisodeRecord(task, int(seeds[0]), success, length, instruction, kept=False)
    return rows, record


def write_episode(root: pathlib.Path, record: EpisodeRecord, rows: TensorDictBase | None) -> EpisodeRecord:
    """Atomically add one episode (its rows only if ``rows`` is given); returns the record as written."""
    record = dataclasses.replace(record, kept=rows is not None)
    staging = staging_dir(root)
    if rows is not None:
        reserve_space(staging, 2 * rows.bytes())  # with room for the consolidated copy
        rows.memmap_(staging / EPISODE_TD_DIR, num_threads=0)
    write_json_atomic(staging / EPISODE_FILE, record.to_json())
    destination = episode_dir(root, record.task, record.seed)
    destination.parent.mkdir(parents=True, exist_ok=True)
    os.replace(staging, destination)
    return record


def scan_episodes(root: pathlib.Path) -> dict[str, dict[int, EpisodeRecord]]:
    """Records of all finished episodes, by task then seed."""
    found: dict[str, dict[int, EpisodeRecord]] = {}
    for path in sorted((root / EPISODES_DIR).glob("*/seed-*")):
        inside(root, str(path.relative_to(root)), root / EPISODES_DIR)  # no symlink out of the dataset
        try:
            record = EpisodeRecord(**read_json(path / EPISODE_FILE))
            home = episode_dir(root, record.task, record.seed)
        except (OSError, ValueError, TypeError) as err:
            raise DatasetError(f"{path}: unreadable episode record ({err}); "
                               "delete this folder to re-collect it") from err
        if home != path:  # its rows are read (and deleted) by task and seed
            raise DatasetError(f"{path}: episode record names task {record.task!r} seed {record.seed!r}, not this "
                               "folder; delete this folder to re-collect it")
        found.setdefault(record.task, {})[record.seed] = record
    return found


def episode_rows_dir(root: pathlib.Path, record: EpisodeRecord) -> pathlib.Path:
    """Folder of an episode's own rows (removed once they are in the consolidated copy)."""
    return episode_dir(root, record.task, record.seed) / EPISODE_TD_DIR


def load_episode_rows(root: pathlib.Path, record: EpisodeRecord) -> TensorDict:
    """The stored rows of a kept episode, checked against its record."""
    path = episode_rows_dir(root, record)
    rows = load_memmap_checked(path)
    if rows.shape[0] != record.length:
        raise DatasetError(f"{path}: {rows.shape[0]} rows but the record says {record.length}")
    return rows
