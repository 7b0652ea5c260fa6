"""Import a LeRobotDataset v3.0 folder (as written by ``dataset export``) as a dust-rl dataset.

Reads the parquet tables with pyarrow and decodes the camera videos with PyAV,
streaming episode by episode into the consolidated memmap layout. Our own
metadata comes back from ``meta/dust_rl.json`` when present; otherwise it is
derived from ``meta/info.json`` (no env id: such a dataset cannot be extended
by ``collect``). Images come back as decoded H.264, i.e. close to but not
bit-equal with the originals; everything else is exact.
"""

from __future__ import annotations

import collections
import itertools
import os
import pathlib
import shutil
import uuid
from collections.abc import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tensordict import TensorDict

from .episodes import EpisodeRecord
from .errors import DatasetError
from .finalize import consolidate
from .layout import FORMAT_VERSION, read_json
from .lerobot_export import COLUMNS, DUST_META_FILE, IMAGE_PREFIX
from .metadata import package_versions
from .video import read_mp4


def import_lerobot(source: str | pathlib.Path, out: str | pathlib.Path, progress: bool = True) -> dict:
    """Convert the LeRobot v3 folder ``source`` into a new dust-rl dataset at ``out``; returns its metadata."""
    source, out = pathlib.Path(source), pathlib.Path(out)
    if out.exists():
        raise FileExistsError(f"{out} already exists; choose a new --out")
    reader = _LeRobotFolder(source)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex}.tmp")
    tmp.mkdir()
    try:
        meta = consolidate(tmp, reader.meta, reader.records, reader.rows_of, reader.env_state_dims, progress)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return meta


class _LeRobotFolder:
    """Tables and videos of one LeRobot v3 folder, served episode by episode in order."""

    def __init__(self, root: pathlib.Path) -> None:
        self.root = root
        try:
            self.info = read_json(root / "meta/info.json")
        except (OSError, ValueError) as err:
            raise DatasetError(f"{root}: not a readable LeRobot dataset (meta/info.json: {err})") from err
        if not str(self.info.get("codebase_version", "")).startswith("v3"):
            raise DatasetError(f"{root}: LeRobot format {self.info.get('codebase_version')!r}; only v3.x is supported")
        features = self.info.get("features", {})
        self.cameras = [key.removeprefix(IMAGE_PREFIX) for key, ft in features.items() if ft.get("dtype") == "video"]
        missing = [name for name in (*COLUMNS, "frame_index", "task_index") if name not in features]
        if missing or not self.cameras:
            raise DatasetError(f"{root}: LeRobot dataset lacks features {missing or ['observation.images.*']}")
        self.frames = self._read_frames()
        self.episodes = sorted(self._read_table("meta/episodes").to_pylist(), key=lambda e: e["episode_index"])
        tasks = self._read_table("meta/tasks.parquet").to_pylist()
        self.tasks = {row["task_index"]: row.get("task", row.get("__index_level_0__")) for row in tasks}
        self.meta = self._dataset_meta()
        self.records = [self._record(episode) for episode in self.episodes]
        self.env_state_dims = self.meta.get("environment_state_dims") or {
            record.task: self.frames["observation.environment_state"].shape[-1] for record in self.records}
        self._videos = {camera: self._video_frames(IMAGE_PREFIX + camera) for camera in self.cameras}
        self._next = 0

    def _read_table(self, relative: str) -> pa.Table:
        path = self.root / relative
        files = sorted(path.rglob("*.parquet")) if path.is_dir() else [path]
        try:
            return pa.concat_tables([pq.read_table(file) for file in files])
        except (OSError, ValueError, pa.ArrowException) as err:
            raise DatasetError(f"{path}: unreadable parquet ({err})") from err

    def _read_frames(self) -> dict[str, torch.Tensor]:
        table = self._read_table("data")
        if "index" in table.column_names:
            table = table.sort_by("index")
        columns = {}
        for name in (*COLUMNS, "frame_index", "task_index"):
            column = table.column(name).combine_chunks()
            if pa.types.is_fixed_size_list(column.type):
                values = column.flatten().to_numpy().reshape(len(column), column.type.list_size)
            else:
                values = column.to_numpy(zero_copy_only=False)
                values = values.reshape(-1, 1) if name.startswith("next.") else values
            columns[name] = torch.from_numpy(np.array(values))  # a writable copy
        return columns

    def _dataset_meta(self) -> dict:
        path = self.root / DUST_META_FILE
        if path.is_file():
            meta = read_json(path)
        else:
            height, width, _ = self.info["features"][IMAGE_PREFIX + self.cameras[0]]["shape"]
            meta = {"env_id": None, "env_kwargs": {}, "start_seed": 0, "noise_std": 0.0, "keep_failed": True,
                    "spec": {"cameras": self.cameras, "image_shape": [height, width, 3],
                             "state_dim": self.frames["observation.state"].shape[-1],
                             "action_dim": self.frames["action"].shape[-1],
                             "control_hz": float(self.info["fps"]), "fps": int(self.info["fps"])}}
        return {**meta, "format_version": FORMAT_VERSION, "source": f"lerobot:{self.root.resolve()}",
                "episodes_per_task": dict(collections.Counter(e.get("dust_rl/task", "lerobot") for e in self.episodes)),
                "data": None, "versions": package_versions()}

    def _record(self, episode: dict) -> EpisodeRecord:
        start = episode["dataset_from_index"]
        instruction = self.tasks[int(self.frames["task_index"][start])]
        return EpisodeRecord(episode.get("dust_rl/task", "lerobot"), episode.get("dust_rl/seed", episode["episode_index"]),
                             episode.get("dust_rl/success", True), episode["length"], instruction, kept=True)

    def _video_frames(self, key: str) -> Iterator[np.ndarray]:
        """All frames of ``key`` in episode order, across the video files the episodes point to."""
        files = [self.root / self.info["video_path"].format(
            video_key=key, chunk_index=e[f"videos/{key}/chunk_index"], file_index=e[f"videos/{key}/file_index"])
            for e in self.episodes]
        return itertools.chain.from_iterable(read_mp4(file) for file in dict.fromkeys(files))

    def rows_of(self, record: EpisodeRecord) -> TensorDict:
        """Rows of the next episode (the videos are decoded in one pass, so episodes come in order)."""
        if self.records[self._next] is not record:
            raise RuntimeError("LeRobot episodes must be read in order")
        episode = self.episodes[self._next]
        self._next += 1
        start, end = episode["dataset_from_index"], episode["dataset_to_index"]
        rows = TensorDict({key: self.frames[name][start:end] for name, key in COLUMNS.items()},
                          batch_size=[end - start])
        env_state = rows.get(("observation", "environment_state"))[:, :self.env_state_dims[record.task]]
        rows.set(("observation", "environment_state"), env_state)
        rows.set("frame_index", self.frames["frame_index"][start:end])
        for camera, frames in self._videos.items():
            images = list(itertools.islice(frames, end - start))
            if len(images) != end - start:
                raise DatasetError(f"{self.root}: video of {camera} ends before episode {episode['episode_index']}")
            rows.set(("observation", "image", camera), torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2))
        return rows
