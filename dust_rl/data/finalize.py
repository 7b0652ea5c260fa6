"""Build the consolidated, fast-loading copy of a dataset from its finished episodes.

All selected episodes are copied into one memmap TensorDict ``[N]`` (rows in
task, then seed order) with ``episode``, ``task_index``, ``instruction_index`` and
``seed`` columns, its statistics are computed, and ``meta.json`` is switched to it
in one atomic replace. Only then are the per-episode row folders of consolidated
episodes and older consolidated copies deleted, so the rows exist once on disk
and a kill at any point leaves a readable dataset; a later finalisation (more
episodes or tasks) reads already-consolidated episodes back from the current copy.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import uuid
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tqdm import tqdm

from dust_rl.errors import DatasetError
from dust_rl.keys import ENV_STATE_KEY
from dust_rl.storage.disk_space import allocate_files
from dust_rl.storage.memmap_io import load_memmap_checked

from .episodes import EpisodeRecord, episode_rows_dir, load_episode_rows, scan_episodes
from .layout import DATA_PREFIX, META_FILE, staging_dir, write_json_atomic
from .metadata import read_meta
from .selection import select_episodes
from .stats import compute_stats

INDEX_COLUMNS = ("episode", "task_index", "instruction_index", "seed")


def finalize_dataset(root: pathlib.Path, progress: bool = True) -> dict:
    """Consolidate the episodes that ``meta.json`` asks for; returns the (new) metadata.

    Does nothing if the consolidated copy already holds exactly those episodes.
    Raises :class:`DatasetError` if some task still lacks finished episodes.
    """
    meta = read_meta(root)
    episodes = _selected_episodes(root, meta)
    if meta.get("data") and [(e["task"], e["seed"]) for e in meta["episodes"]] == [(r.task, r.seed) for r in episodes]:
        return meta
    rows_of = _row_source(root, meta)
    env_state_dims = {}
    for record in episodes:
        if record.task not in env_state_dims:
            env_state_dims[record.task] = rows_of(record).get(ENV_STATE_KEY).shape[-1]
    meta = consolidate(root, meta, episodes, rows_of, env_state_dims, progress)
    for record in episodes:
        _remove_dir(episode_rows_dir(root, record))
    return meta


def consolidate(root: pathlib.Path, meta: dict, episodes: list[EpisodeRecord],
                rows_of: Callable[[EpisodeRecord], TensorDictBase], env_state_dims: dict[str, int],
                progress: bool = True) -> dict:
    """Write ``episodes`` as the dataset's data and switch ``meta.json`` to it atomically.

    Args:
        rows_of: an episode's rows; called once per episode, in order (so it may stream).
        env_state_dims: privileged-state size per task; tasks differ, so the column is
            zero-padded to the largest.
    """
    tasks = list(dict.fromkeys([*meta["episodes_per_task"], *(record.task for record in episodes)]))
    instructions = list(dict.fromkeys(record.instruction for record in episodes))
    total = sum(record.length for record in episodes)
    staging = staging_dir(root)
    out, table, start = None, [], 0
    for index, record in enumerate(tqdm(episodes, desc="consolidating", disable=not progress)):
        rows = rows_of(record)
        if out is None:
            out = _allocate(rows, total, max(env_state_dims.values()), staging / "data")
        block = out[start:start + record.length]
        block.update_(rows.exclude(ENV_STATE_KEY, *INDEX_COLUMNS))
        block.get(ENV_STATE_KEY)[:, :env_state_dims[record.task]] = rows.get(ENV_STATE_KEY)
        instruction_index = instructions.index(record.instruction)
        for column, value in zip(INDEX_COLUMNS, (index, tasks.index(record.task), instruction_index, record.seed)):
            block.get(column).fill_(value)
        table.append({"index": index, "task": record.task, "seed": record.seed, "length": record.length,
                      "success": record.success, "instruction_index": instruction_index, "row_start": start})
        start += record.length

    data_name = f"{DATA_PREFIX}{uuid.uuid4().hex[:12]}"
    os.replace(staging / "data", root / data_name)
    shutil.rmtree(staging)
    meta = {**meta, "data": data_name, "num_rows": total, "tasks": tasks, "instructions": instructions,
            "episodes": table, "environment_state_dims": env_state_dims, "stats": compute_stats(out)}
    write_json_atomic(root / META_FILE, meta)
    for old in root.glob(f"{DATA_PREFIX}*"):
        if old.name != data_name:
            _remove_dir(old)
    return meta


def _selected_episodes(root: pathlib.Path, meta: dict) -> list[EpisodeRecord]:
    records = scan_episodes(root)
    selected = []
    for task, count in meta["episodes_per_task"].items():
        chosen = select_episodes(records.get(task, {}), meta["start_seed"], count, meta["keep_failed"])
        if chosen is None:
            raise DatasetError(f"{root}: task {task!r} has fewer than {count} finished successful episodes; "
                               "re-run the same collect command to finish it")
        selected += chosen
    return selected


def _row_source(root: pathlib.Path, meta: dict) -> Callable[[EpisodeRecord], TensorDictBase]:
    """Where an episode's rows are: its own folder if present, else the current consolidated copy."""
    consolidated = load_memmap_checked(root / meta["data"]) if meta.get("data") else None
    spans = {(e["task"], e["seed"]): (e["row_start"], e["length"]) for e in meta.get("episodes", [])}

    def rows_of(record: EpisodeRecord) -> TensorDictBase:
        if episode_rows_dir(root, record).exists():
            return load_episode_rows(root, record)
        if consolidated is None or (record.task, record.seed) not in spans:
            raise DatasetError(f"{root}: the rows of {record.task} seed {record.seed} are missing; "
                               f"delete {episode_rows_dir(root, record).parent} to re-collect it")
        start, length = spans[record.task, record.seed]
        rows = consolidated[start:start + length]
        env_state = rows.get(ENV_STATE_KEY)[:, :meta["environment_state_dims"][record.task]]
        return rows.exclude(ENV_STATE_KEY).set(ENV_STATE_KEY, env_state)

    return rows_of


def _allocate(rows: TensorDictBase, total: int, env_state_dim: int, path: pathlib.Path) -> TensorDict:
    """An uninitialised memmap TensorDict ``[total]`` with the entries of ``rows`` plus the index columns."""
    template = rows.exclude(*INDEX_COLUMNS)[0].clone()
    template.set(ENV_STATE_KEY, torch.zeros(env_state_dim, dtype=template.get(ENV_STATE_KEY).dtype))
    for column in INDEX_COLUMNS:
        template.set(column, torch.zeros((), dtype=torch.int64))
    out = template.expand(total).memmap_like(path, num_threads=0)
    allocate_files(path)
    out.get(ENV_STATE_KEY).zero_()
    return out


def _remove_dir(path: pathlib.Path) -> None:
    """Rename first (atomic), then delete: a half-deleted folder is never mistaken for a whole one."""
    if path.exists():
        doomed = path.with_name(f".{path.name}.{uuid.uuid4().hex}.deleting")
        os.replace(path, doomed)
        shutil.rmtree(doomed)
