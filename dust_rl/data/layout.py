"""On-disk layout of a demonstration dataset and atomic file writes.

A dataset folder holds::

    meta.json                     collection config, env spec, versions; after finalising
                                  also the episode table, statistics and the data folder name
    episodes/<task>/seed-000012/  one finished episode: episode.json, plus td/ (its rows, a
                                  memmap TensorDict) while a kept episode is not yet consolidated
    data-<token>/                 consolidated memmap TensorDict of all kept rows (fast loading)
    .staging/                     work in progress; never read, cleared by the next collection

Every finished piece is written under ``.staging`` and moved into place with
``os.replace``, and ``meta.json`` is replaced whole, so a killed process leaves
either the old state or the new one, never a half-written file that a reader trusts.
"""

from __future__ import annotations

import json
import pathlib
import shutil
import uuid

from dust_rl.storage.atomic_files import write_json_atomic  # noqa: F401  (the dataset writers' import)

FORMAT_VERSION = 1
META_FILE = "meta.json"
EPISODES_DIR = "episodes"
STAGING_DIR = ".staging"
DATA_PREFIX = "data-"
EPISODE_FILE = "episode.json"
EPISODE_TD_DIR = "td"


def episode_dir(root: pathlib.Path, task: str, seed: int) -> pathlib.Path:
    """Folder of the episode of ``task`` started from ``reset(seed=seed)``."""
    return root / EPISODES_DIR / task / f"seed-{seed:06d}"


def staging_dir(root: pathlib.Path) -> pathlib.Path:
    """A fresh, empty folder under ``.staging`` (same filesystem, so ``os.replace`` is atomic)."""
    path = root / STAGING_DIR / uuid.uuid4().hex
    path.mkdir(parents=True)
    return path


def clear_staging(root: pathlib.Path) -> None:
    """Remove what an interrupted writer left behind."""
    shutil.rmtree(root / STAGING_DIR, ignore_errors=True)


def read_json(path: pathlib.Path) -> dict:
    with open(path) as f:
        return json.load(f)
