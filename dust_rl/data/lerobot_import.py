"""Import a LeRobotDataset v3.0 folder as a dust-rl dataset.

Reads the parquet tables with pyarrow and decodes the camera videos with PyAV,
streaming episode by episode into the consolidated memmap layout. The env the
data belongs to comes from one of two places:

* ``meta/dust_rl.json``, written by ``dataset export``: env id and kwargs, spec,
  and per episode the task, seed and success (columns ``dust_rl/*``);
* the caller (``env_id``, ``task``, ``env_kwargs``) for any other LeRobot v3
  dataset. The env is built once and the dataset must fit its spaces:
  ``observation.state`` and ``action`` of its sizes, a video feature
  ``observation.images.<camera>`` (LeRobot's name; the env's own
  ``observation.image.<camera>`` is read too) of its image shape for each of
  its cameras (other video features are left out), and ``fps`` equal to its
  control rate.
  Columns such a dataset lacks are filled in: ``expert_action`` is the action,
  the privileged ``observation.environment_state`` is empty, the reward 0, and
  each episode counts as a successful demonstration that ends (terminated) at
  its last frame.

Everything in the folder is untrusted (datasets are downloaded and shared), so
before anything is written: ``video_path`` may use only its three fields and
every file must lie inside the folder (no absolute path, ``..`` or symlink
out); each episode must be at least one frame long, lie inside the data, not
overlap another, and its rows must carry its index; ``dust_rl.json`` must be a
JSON object with its keys. Each problem is a one-line :class:`DatasetError`.
Images come back as decoded H.264, i.e. close to but not bit-equal with the
originals; everything else is exact.
"""

from __future__ import annotations

import collections
import itertools
import json
import math
import os
import pathlib
import re
import shutil
import string
import uuid
from collections.abc import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tensordict import TensorDict

from dust_rl.errors import DatasetError
from dust_rl.keys import ENV_STATE_KEY, EXPERT_ACTION_KEY, IMAGE_KEY, flat_name
from dust_rl.storage.config_json import package_versions
from dust_rl.storage.paths import SAFE_NAME, inside

from .episodes import EpisodeRecord
from .finalize import consolidate
from .layout import FORMAT_VERSION, read_json
from .lerobot_export import COLUMNS, DUST_META_FILE, IMAGE_PREFIX
from .metadata import recorded_env_spec, spec_mismatches
from .video import read_mp4

INFO_FILE = "meta/info.json"
TASKS_FILE = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
DATA_DIR = "data"
STATE, ACTION = "observation.state", "action"
# LeRobot's own per-frame columns that the import needs (timestamps are implied by frame_index / fps).
INDEX_COLUMNS = ("frame_index", "episode_index", "index", "task_index")
# Entries of dust_rl.json that the import keeps, with their JSON types; the rest is recomputed.
DUST_META_TYPES = {"env_id": str, "env_kwargs": dict, "spec": dict, "start_seed": int, "noise_std": float,
                   "keep_failed": bool}
_VIDEO_FIELDS = ("video_key", "chunk_index", "file_index")
_INDEX_FORMAT = re.compile(r"\d*d?")
_FLAGS = ("next.done", "next.terminated", "next.truncated", "next.success")
# A camera's video feature: LeRobot's name (what the export writes), else the env's observation key.
VIDEO_PREFIXES = (IMAGE_PREFIX, flat_name(IMAGE_KEY) + ".")


def import_lerobot(source: str | pathlib.Path, out: str | pathlib.Path, env_id: str | None = None,
                   task: str | None = None, env_kwargs: dict | None = None, progress: bool = True) -> dict:
    """Convert the LeRobot v3 folder ``source`` into a new dust-rl dataset at ``out``; returns its metadata.

    Args:
        source: the LeRobot folder.
        out: the new dataset folder (must not exist; written under a temporary name, then renamed).
        env_id: the env the data was recorded in; required (with ``task``) unless the folder has
            ``meta/dust_rl.json``, which it then overrides.
        task: the env task all episodes belong to.
        env_kwargs: env constructor arguments (image size, cameras...) that make it fit the data.
        progress: show a progress bar.

    Raises:
        DatasetError: an unreadable, inconsistent or unsafe folder, or one that does not fit the env.
        ConfigError: an unknown env id or task, or env kwargs the env refuses.
        FileExistsError: ``out`` exists.
    """
    source, out = pathlib.Path(source), pathlib.Path(out)
    if out.exists():
        raise FileExistsError(f"{out} already exists; choose a new --out")
    target = _env_target(env_id, task, env_kwargs) if env_id is not None or task is not None or env_kwargs else None
    reader = _LeRobotFolder(source, target)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex}.tmp")
    tmp.mkdir()
    try:
        meta = consolidate(tmp, reader.meta, reader.records, reader.rows_of, reader.env_state_dims, progress)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return meta


def _env_target(env_id: str | None, task: str | None, env_kwargs: dict | None) -> dict:
    """The metadata a foreign dataset gets from the env it is imported for (the env is built once)."""
    from dust_rl.envs.factory import check_tasks, make_env
    from dust_rl.errors import ConfigError

    if env_id is None or task is None:
        raise ConfigError("give both the env id and the task the dataset was recorded in (--env and --task)")
    try:
        env_kwargs = json.loads(json.dumps(env_kwargs or {}))  # as it will read back from meta.json
    except (TypeError, ValueError) as err:
        raise ConfigError(f"env kwargs must be JSON values (they are stored in meta.json): {err}") from err
    check_tasks(env_id, env_kwargs, [task])
    env = make_env(env_id, {**env_kwargs, "task": task})
    spec = recorded_env_spec(env)
    env.close()
    return {"env_id": env_id, "env_kwargs": env_kwargs, "task": task, "spec": spec}


class _LeRobotFolder:
    """Tables and videos of one LeRobot v3 folder, checked, served episode by episode in order.

    Args:
        root: the folder.
        target: from :func:`_env_target`, or None to take the env from ``meta/dust_rl.json``.
    """

    def __init__(self, root: pathlib.Path, target: dict | None) -> None:
        self.root = root
        self.info = self._read_info()
        self.fps = self.info["fps"]
        self._video_template = self._check_video_template(self.info.get("video_path"))
        self.dust = self._read_dust_meta() if target is None else None
        base = target if target is not None else self.dust
        self.spec = base["spec"]
        self._check_features(target)
        self.frames = self._read_frames()
        self.tasks = self._read_tasks()
        self.episodes = self._read_episodes()
        self._fill_missing_columns()
        self.records = [self._record(episode, target) for episode in self.episodes]
        if target is None:
            self._check_recorded_env()
        width = self.frames["observation.environment_state"].shape[-1]
        self.env_state_dims = self._env_state_dims(width)
        self.meta = self._dataset_meta(base)
        self._video_files = [{camera: self._video_file(camera, episode) for camera in self.spec["cameras"]}
                             for episode in self.episodes]  # every path checked before anything is written
        self._videos = {camera: _VideoStream(self.spec["image_shape"][:2]) for camera in self.spec["cameras"]}
        self._next = 0

    # -- files ----------------------------------------------------------------
    def _path(self, relative: str) -> pathlib.Path:
        return inside(self.root, relative, self.root)

    def _read_info(self) -> dict:
        try:
            info = read_json(self._path(INFO_FILE))
        except (OSError, ValueError) as err:
            raise DatasetError(f"{self.root}: not a readable LeRobot dataset ({INFO_FILE}: {err})") from err
        if not isinstance(info, dict) or not isinstance(info.get("features"), dict):
            raise DatasetError(f"{self.root / INFO_FILE}: not a LeRobot info file (no features)")
        if not str(info.get("codebase_version", "")).startswith("v3"):
            raise DatasetError(f"{self.root}: LeRobot format {info.get('codebase_version')!r}; only v3.x is supported")
        fps = info.get("fps")
        if not (_is_json(fps, float) and fps > 0):
            raise DatasetError(f"{self.root / INFO_FILE}: fps must be a positive number, got {fps!r}")
        return info

    def _check_video_template(self, template: object) -> str:
        """``video_path``: literal text and the fields ``{video_key}``, ``{chunk_index:03d}``, ``{file_index:03d}``."""
        where = self.root / INFO_FILE
        if not isinstance(template, str):
            raise DatasetError(f"{where}: video_path must be a string, got {template!r}")
        try:
            fields = [(name, spec, conversion) for _, name, spec, conversion in string.Formatter().parse(template)
                      if name is not None]
        except ValueError as err:
            raise DatasetError(f"{where}: video_path {template!r} is not a path template ({err})") from err
        for name, spec, conversion in fields:
            allowed_spec = spec == "" if name == "video_key" else _INDEX_FORMAT.fullmatch(spec or "")
            if name not in _VIDEO_FIELDS or conversion is not None or not allowed_spec:
                raise DatasetError(f"{where}: video_path {template!r} uses {{{name}}}; only {{video_key}}, "
                                   "{chunk_index:03d} and {file_index:03d} are allowed")
        return template

    def _read_dust_meta(self) -> dict:
        path = self.root / DUST_META_FILE
        if not path.is_file():
            raise DatasetError(f"{self.root}: no {DUST_META_FILE} (not exported by dust-rl): give the env the data "
                               "was recorded in (--env, --task; --image-size, --cameras to match its videos)")
        try:
            meta = read_json(self._path(DUST_META_FILE))
        except (OSError, ValueError) as err:
            raise DatasetError(f"{path}: unreadable ({err})") from err
        if not isinstance(meta, dict):
            raise DatasetError(f"{path}: expected a JSON object, got {type(meta).__name__}")
        bad = [key for key, kind in DUST_META_TYPES.items() if not _is_json(meta.get(key), kind)]
        if bad:
            raise DatasetError(f"{path}: missing or malformed {bad}; re-export the dataset, or import it with "
                               "--env and --task")
        return meta

    def _check_recorded_env(self) -> None:
        """Raise unless ``dust_rl.json`` names a dust-rl env that takes its kwargs, has every episode's task and
        renders what its spec records (whose image size sizes the decoded videos)."""
        from dust_rl.envs.factory import check_tasks
        from dust_rl.errors import ConfigError

        where = self.root / DUST_META_FILE
        tasks = sorted({record.task for record in self.records})
        try:
            check_tasks(self.dust["env_id"], self.dust["env_kwargs"], tasks)
            env = _env_target(self.dust["env_id"], tasks[0], self.dust["env_kwargs"])
        except ConfigError as err:
            raise DatasetError(f"{where}: {err}; re-export the dataset, or import it with --env and --task") from err
        problems = spec_mismatches(self.spec, env["spec"])
        if problems:
            raise DatasetError(f"{where} does not match its env ({'; '.join(problems)}); re-export the dataset, or "
                               "import it with --env and --task")

    def _read_table(self, relative: str, columns: list[str] | None = None) -> pa.Table:
        """The parquet file ``relative``, or all parquet files under that folder, concatenated."""
        path = self._path(relative)
        files = [self._path(str(file.relative_to(self.root)))
                 for file in (sorted(path.rglob("*.parquet")) if path.is_dir() else [path])]
        if not files:
            raise DatasetError(f"{path}: no parquet files")
        tables = []
        for file in files:
            try:
                names = pq.read_schema(file).names
                absent = [name for name in columns or [] if name not in names]
                table = None if absent else pq.read_table(file, columns=columns)
            except (OSError, ValueError, pa.ArrowException) as err:
                raise DatasetError(f"{file}: unreadable parquet ({err})") from err
            if absent:
                raise DatasetError(f"{file}: lacks the columns {absent} that {INFO_FILE} lists")
            tables.append(table)
        return pa.concat_tables(tables)

    # -- features and tables ----------------------------------------------------
    def _check_features(self, target: dict | None) -> None:
        """Raise one :class:`DatasetError` naming every feature that is missing or does not fit ``spec``."""
        features, spec = self.info["features"], self.spec
        whole = (f"env {target['env_id']} {target['env_kwargs']} (task {target['task']})" if target is not None
                 else str(self.root / DUST_META_FILE))
        against = "the env" if target is not None else DUST_META_FILE
        problems = [f"{name}: missing" for name in (STATE, ACTION, *INDEX_COLUMNS) if name not in features]
        for name, size in ((STATE, spec.get("state_dim")), (ACTION, spec.get("action_dim"))):
            if name in features and _feature_shape(features[name]) != [size]:
                problems.append(f"{name}: shape {_feature_shape(features[name])}, {against} has [{size}]")
        cameras = spec.get("cameras")
        if not (isinstance(cameras, list) and cameras and all(isinstance(c, str) and SAFE_NAME.fullmatch(c)
                                                             for c in cameras)):
            problems.append(f"cameras: {against} names {cameras!r}, not a list of camera names")
            cameras = []
        for camera in cameras:
            key = self._video_key(camera)
            feature = features.get(key)
            if not isinstance(feature, dict) or feature.get("dtype") != "video":
                found = "missing" if feature is None else f"{feature!r}, not a video"
                problems.append(f"{key}: {found} ({against} has cameras {cameras}; "
                                "choose others with the env's cameras argument)")
            elif _image_shape(feature) != list(spec.get("image_shape") or []):
                problems.append(f"{key}: shape {_image_shape(feature)}, {against} renders "
                                f"{spec.get('image_shape')} (set the env's image_size)")
        if self.fps != spec.get("fps") or float(self.fps) != spec.get("control_hz"):
            problems.append(f"fps: dataset records {self.fps} frames/s, {against} has fps {spec.get('fps')!r} "
                            f"and control rate {spec.get('control_hz')!r} Hz")
        if problems:
            raise DatasetError(f"{self.root} does not fit {whole}: " + "; ".join(problems))

    def _read_frames(self) -> dict[str, torch.Tensor]:
        """The per-frame columns, in ``index`` order, which must be 0, 1, 2, ..."""
        wanted = [name for name in (*COLUMNS, *INDEX_COLUMNS) if name in self.info["features"]]
        table = self._read_table(DATA_DIR, wanted).sort_by("index")
        columns = {name: _column(table.column(name), name, self.root / DATA_DIR) for name in wanted}
        if not torch.equal(columns["index"].long(), torch.arange(table.num_rows)):
            raise DatasetError(f"{self.root / DATA_DIR}: frame index column is not 0..{table.num_rows - 1} "
                               "(duplicate or missing frames)")
        return columns

    def _read_tasks(self) -> dict[int, str]:
        rows = self._read_table(TASKS_FILE).to_pylist()
        tasks = {row.get("task_index"): row.get("task", row.get("__index_level_0__")) for row in rows}
        if not all(isinstance(i, int) and isinstance(text, str) for i, text in tasks.items()):
            raise DatasetError(f"{self.root / TASKS_FILE}: expected task_index and task text columns")
        return tasks

    def _read_episodes(self) -> list[dict]:
        """Episode rows sorted by index: each >= 1 frames inside the data, none overlapping, its frames its own."""
        where = self.root / EPISODES_DIR
        needed = ["episode_index", "length", "dataset_from_index", "dataset_to_index"]
        for camera in self.spec["cameras"]:
            needed += [f"videos/{self._video_key(camera)}/{name}" for name in ("chunk_index", "file_index",
                                                                              "from_timestamp")]
        table = self._read_table(EPISODES_DIR)
        missing = [name for name in needed if name not in table.column_names]
        if missing:
            raise DatasetError(f"{where}: episode table lacks columns {missing}")
        episodes, rows = table.to_pylist(), len(self.frames["index"])
        if not episodes:
            raise DatasetError(f"{where}: no episodes")
        for episode in episodes:
            index, length = episode["episode_index"], episode["length"]
            start, end = episode["dataset_from_index"], episode["dataset_to_index"]
            malformed = [name for name in needed if not _is_json(episode[name], float if "timestamp" in name else int)
                         or episode[name] < 0 and name != "length"]
            if malformed:
                raise DatasetError(f"{where}: episode {index!r} has malformed or negative {malformed}")
            if length < 1:
                raise DatasetError(f"{where}: episode {index} has length {length}; episodes need at least one frame")
            if end - start != length or end > rows:
                raise DatasetError(f"{where}: episode {index} spans frames {start}..{end} with length {length}, "
                                   f"outside the {rows} frames of the data or of another length")
        spans = sorted((e["dataset_from_index"], e["dataset_to_index"], e["episode_index"]) for e in episodes)
        for (_, end, first), (start, _, second) in zip(spans, spans[1:]):
            if start < end:
                raise DatasetError(f"{where}: episodes {first} and {second} overlap (frames {start}..{end})")
        for episode in episodes:
            index, start, end = episode["episode_index"], episode["dataset_from_index"], episode["dataset_to_index"]
            carried = self.frames["episode_index"][start:end]
            if not bool((carried == index).all()):
                raise DatasetError(f"{where}: frames {start}..{end} are listed as episode {index} but carry "
                                   f"episode_index {sorted(set(carried.tolist()))}")
            task_index = int(self.frames["task_index"][start])
            if task_index not in self.tasks:
                raise DatasetError(f"{where}: episode {index} has task_index {task_index}, not in {TASKS_FILE}")
        return sorted(episodes, key=lambda e: e["episode_index"])

    def _fill_missing_columns(self) -> None:
        """Columns a foreign dataset may lack (see module doc), built from the episode table."""
        frames, rows = self.frames, len(self.frames["index"])
        last = torch.zeros(rows, dtype=torch.bool)
        last[[episode["dataset_to_index"] - 1 for episode in self.episodes]] = True
        defaults = {flat_name(ENV_STATE_KEY): torch.zeros(rows, 0), EXPERT_ACTION_KEY: frames[ACTION],
                    "next.reward": torch.zeros(rows), "next.done": last, "next.terminated": last,
                    "next.truncated": torch.zeros(rows, dtype=torch.bool), "next.success": last}
        for name, value in defaults.items():
            frames.setdefault(name, value)
        for name in COLUMNS:  # per-step entries are [rows, D] (flags and reward [rows, 1])
            frames[name] = (frames[name].bool() if name in _FLAGS else frames[name].float()).reshape(rows, -1)

    def _record(self, episode: dict, target: dict | None) -> EpisodeRecord:
        instruction = self.tasks[int(self.frames["task_index"][episode["dataset_from_index"]])]
        if target is not None:
            return EpisodeRecord(target["task"], episode["episode_index"], True, episode["length"], instruction,
                                 kept=True)
        task, seed = episode.get("dust_rl/task"), episode.get("dust_rl/seed", episode["episode_index"])
        success = episode.get("dust_rl/success", True)
        if not (isinstance(task, str) and _is_json(seed, int) and isinstance(success, bool)):
            raise DatasetError(f"{self.root / EPISODES_DIR}: episode {episode['episode_index']} has missing or "
                               f"malformed dust_rl/task, seed or success ({task!r}, {seed!r}, {success!r}); "
                               "import it with --env and --task")
        return EpisodeRecord(task, seed, success, episode["length"], instruction, kept=True)

    def _env_state_dims(self, width: int) -> dict[str, int]:
        tasks = {record.task for record in self.records}
        dims = (self.dust or {}).get("environment_state_dims") or {task: width for task in tasks}
        if not (isinstance(dims, dict) and tasks <= set(dims)
                and all(isinstance(d, int) and 0 <= d <= width for d in dims.values())):
            raise DatasetError(f"{self.root / DUST_META_FILE}: environment_state_dims {dims!r} must give each task "
                               f"{sorted(tasks)} a width in [0, {width}]")
        return {task: dims[task] for task in tasks}

    def _dataset_meta(self, base: dict) -> dict:
        kept = {key: base[key] for key in ("env_id", "env_kwargs", "spec")}
        defaults = {"start_seed": 0, "noise_std": 0.0, "keep_failed": True}
        kept.update({key: base.get(key, value) for key, value in defaults.items()})
        return {**kept, "format_version": FORMAT_VERSION, "source": f"lerobot:{self.root.resolve()}",
                "episodes_per_task": dict(collections.Counter(record.task for record in self.records)),
                "data": None, "versions": package_versions()}

    # -- rows -------------------------------------------------------------------
    def _video_key(self, camera: str) -> str:
        """The feature holding ``camera``'s video: the first of :data:`VIDEO_PREFIXES` the dataset has (LeRobot's
        name when it has neither, for the message that it is missing)."""
        keys = [prefix + camera for prefix in VIDEO_PREFIXES]
        return next((key for key in keys if key in self.info["features"]), keys[0])

    def _video_file(self, camera: str, episode: dict) -> pathlib.Path:
        key = self._video_key(camera)
        chunk, file = episode[f"videos/{key}/chunk_index"], episode[f"videos/{key}/file_index"]
        try:
            relative = self._video_template.format(video_key=key, chunk_index=chunk, file_index=file)
        except (ValueError, TypeError) as err:
            raise DatasetError(f"{self.root / INFO_FILE}: video_path does not format ({err})") from err
        return inside(self.root, relative, self.root / INFO_FILE)

    def rows_of(self, record: EpisodeRecord) -> TensorDict:
        """Rows of the next episode (called once per episode, in order)."""
        if self.records[self._next] is not record:
            raise RuntimeError("LeRobot episodes must be read in order")
        episode, video_files = self.episodes[self._next], self._video_files[self._next]
        self._next += 1
        start, end = episode["dataset_from_index"], episode["dataset_to_index"]
        rows = TensorDict({key: self.frames[name][start:end] for name, key in COLUMNS.items()},
                          batch_size=[end - start])
        env_state = rows.get(ENV_STATE_KEY)[:, :self.env_state_dims[record.task]]
        rows.set(ENV_STATE_KEY, env_state)
        rows.set("frame_index", self.frames["frame_index"][start:end])
        for camera, stream in self._videos.items():
            key = self._video_key(camera)
            first = round(episode[f"videos/{key}/from_timestamp"] * self.fps)
            images = np.stack(stream.read(video_files[camera], first, end - start,
                                          f"episode {episode['episode_index']}"))
            rows.set((*IMAGE_KEY, camera), torch.from_numpy(images).permute(0, 3, 1, 2))
        return rows


class _VideoStream:
    """One camera's ``(H, W)`` frames, decoded forward through its files; reopened for an earlier start."""

    def __init__(self, size: tuple[int, int]) -> None:
        self.size = size
        self.path: pathlib.Path | None = None
        self._frames: Iterator[np.ndarray] = iter(())
        self._position = 0

    def read(self, path: pathlib.Path, first: int, count: int, what: str) -> list[np.ndarray]:
        """Frames ``first .. first + count - 1`` of ``path``."""
        if path != self.path or first < self._position:
            self.path, self._frames, self._position = path, read_mp4(path, self.size), 0
        collections.deque(itertools.islice(self._frames, first - self._position), maxlen=0)  # skip
        frames = list(itertools.islice(self._frames, count))
        self._position = first + len(frames)
        if len(frames) != count:
            raise DatasetError(f"{path}: video ends before {what} (needs frames {first}..{first + count})")
        return frames


def _feature_shape(feature: object) -> list | None:
    return list(feature["shape"]) if isinstance(feature, dict) and isinstance(feature.get("shape"), list) else None


def _image_shape(feature: dict) -> list | None:
    """``[H, W, C]`` of a video feature, also when its ``names`` put the channels first."""
    shape, names = _feature_shape(feature), feature.get("names")
    channels_first = isinstance(names, list) and names[:1] in (["channels"], ["channel"])
    return shape[1:] + shape[:1] if shape and channels_first else shape


def _is_json(value: object, kind: type) -> bool:
    """``isinstance`` for values read from JSON or parquet: a bool is no number; floats must be finite."""
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, kind) and (kind is bool or not isinstance(value, bool))


def _column(column: pa.ChunkedArray, name: str, where: pathlib.Path) -> torch.Tensor:
    """A numeric column as a tensor: scalars ``[N]``, (fixed-size) lists ``[N, D]``."""
    column = column.combine_chunks()
    try:
        if pa.types.is_fixed_size_list(column.type) or pa.types.is_list(column.type):
            widths = set(column.value_lengths().to_pylist()) if pa.types.is_list(column.type) else {
                column.type.list_size}
            if len(widths) > 1 or column.null_count:
                raise ValueError(f"rows of {sorted(widths)[:4]} values or missing rows")
            values = column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), *widths)
        else:
            values = column.to_numpy(zero_copy_only=False)
        if not (np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_):
            raise ValueError(f"{values.dtype} values")
    except (ValueError, pa.ArrowException) as err:
        raise DatasetError(f"{where}: column {name} is not numeric ({err})") from err
    return torch.from_numpy(np.array(values))  # a writable copy
