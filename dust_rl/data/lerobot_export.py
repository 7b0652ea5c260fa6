"""Export a dataset as LeRobotDataset v3.0 (parquet + one H.264 MP4 per camera).

Layout (what LeRobot and torchrl's ``LeRobotExperienceReplay`` read)::

    meta/info.json, meta/stats.json, meta/tasks.parquet
    meta/episodes/chunk-000/file-000.parquet   per-episode lengths, row and video spans
    data/chunk-000/file-000.parquet            one row per step
    videos/observation.images.<cam>/chunk-000/file-000.mp4
    meta/dust_rl.json                          our metadata, for a lossless re-import

LeRobot "tasks" are the language instructions. ``action`` is the executed action and
``expert_action`` the expert's label; they differ only for DART-noised collections,
where a LeRobot policy should train on ``expert_action``. Episodes are stored back to back in
one data file and one video per camera, so episode ``e``'s video span starts at
``dataset_from_index / fps``. Only pyarrow and PyAV are needed, not ``lerobot``.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import uuid

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tensordict import TensorDictBase
from tqdm import tqdm

from dust_rl.errors import DatasetError
from dust_rl.keys import ENV_STATE_KEY, EXPERT_ACTION_KEY, IMAGE_KEY, STATE_KEY

from .dataset import DemoDataset
from .layout import write_json_atomic
from .video import PIX_FMT, VIDEO_CODEC, write_mp4

CODEBASE_VERSION = "v3.0"
DATA_FILE = "data/chunk-000/file-000.parquet"
EPISODES_FILE = "meta/episodes/chunk-000/file-000.parquet"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
DUST_META_FILE = "meta/dust_rl.json"
IMAGE_PREFIX = "observation.images."
# LeRobot column <- dataset entry, for every per-step entry besides images and LeRobot's index columns.
COLUMNS: dict[str, str | tuple[str, ...]] = {
    "observation.state": STATE_KEY,
    "observation.environment_state": ENV_STATE_KEY,
    "action": "action",
    EXPERT_ACTION_KEY: EXPERT_ACTION_KEY,
    "next.reward": ("next", "reward"),
    "next.done": ("next", "done"),
    "next.terminated": ("next", "terminated"),
    "next.truncated": ("next", "truncated"),
    "next.success": ("next", "success"),
}
_IMAGE_STATS_FRAMES = 1000
_DTYPES = {pa.float32(): "float32", pa.int64(): "int64", pa.bool_(): "bool"}


def export_lerobot(dataset: DemoDataset, out: str | pathlib.Path, crf: int = 18, progress: bool = True) -> pathlib.Path:
    """Write ``dataset`` as a LeRobot v3.0 folder at ``out`` (which must not exist yet).

    Written to a temporary sibling folder first and renamed into place, so ``out`` is
    either complete or absent. ``crf`` is the H.264 quality (0 lossless luma, 18 near-transparent).

    Raises:
        FileExistsError: ``out`` exists.
        DatasetError: the frames have an odd height or width. LeRobot keeps frames as H.264 (yuv420p) video, which
            needs even sizes, and a LeRobot user trains on the frames as stored: padded or cropped ones would no
            longer be the dataset's. Refused before anything is written.
    """
    out = pathlib.Path(out)
    if out.exists():
        raise FileExistsError(f"{out} already exists; choose a new --out")
    height, width = dataset.meta["spec"]["image_shape"][:2]
    if height % 2 or width % 2:
        raise DatasetError(f"{dataset.root}: its frames are {height}x{width} px; a LeRobot dataset stores frames as "
                           f"H.264 ({PIX_FMT}) video, which needs even sizes, and padding or cropping would change "
                           "the frames a policy trains on: collect the dataset at an even --image-size (e.g. "
                           f"{height + height % 2}) to export it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex}.tmp")
    try:
        _write(dataset, tmp, crf, progress)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _write(dataset: DemoDataset, root: pathlib.Path, crf: int, progress: bool) -> None:
    meta, data = dataset.meta, dataset.data
    fps = meta["spec"]["fps"]
    video_keys = [IMAGE_PREFIX + camera for camera in dataset.cameras]
    for camera, key in zip(dataset.cameras, video_keys):
        frames = data.get((*IMAGE_KEY, camera))
        write_mp4(root / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=0),
                  (frame.permute(1, 2, 0).numpy() for frame in tqdm(frames, desc=f"encoding {camera}",
                                                                      disable=not progress)), fps, crf)
    frame_index = data.get("frame_index")
    columns = {name: _arrow_column(data.get(key)) for name, key in COLUMNS.items()}
    columns.update({
        "timestamp": pa.array((frame_index.double() / fps).float().numpy()),
        "frame_index": pa.array(frame_index.numpy()),
        "episode_index": pa.array(data.get("episode").numpy()),
        "index": pa.array(np.arange(len(dataset), dtype=np.int64)),
        "task_index": pa.array(data.get("instruction_index").numpy()),
    })
    _write_parquet(root / DATA_FILE, pa.table(columns))
    _write_parquet(root / EPISODES_FILE, _episodes_table(meta, video_keys, fps))
    _write_parquet(root / "meta/tasks.parquet", _tasks_table(dataset.instructions))
    names = _feature_names(meta, dataset.tasks, columns["observation.environment_state"])
    features = {name: _feature(columns[name], names.get(name)) for name in columns}
    features.update({key: _video_feature(meta["spec"]["image_shape"], fps) for key in video_keys})
    write_json_atomic(root / "meta/info.json", {
        "codebase_version": CODEBASE_VERSION, "robot_type": meta["env_id"],
        "total_episodes": dataset.num_episodes, "total_frames": len(dataset), "total_tasks": len(dataset.instructions),
        "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 500, "fps": fps,
        "splits": {"train": f"0:{dataset.num_episodes}"}, "data_path": DATA_PATH, "video_path": VIDEO_PATH,
        "features": features,
    })
    write_json_atomic(root / "meta/stats.json", {**meta["stats"], **_image_stats(data, dataset.cameras)})
    write_json_atomic(root / DUST_META_FILE, {key: value for key, value in meta.items() if key != "data"})


def _arrow_column(values: torch.Tensor) -> pa.Array:
    """``[N]``/``[N, 1]`` -> scalar column; ``[N, D]`` -> fixed-size list column (LeRobot's Sequence)."""
    array = values.numpy()
    if array.ndim == 1 or array.shape[1:] == (1,):
        return pa.array(array.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(pa.array(array.reshape(-1)), array.shape[1])


def _feature_names(meta: dict, tasks: list[str], env_state: pa.Array) -> dict[str, list[str]]:
    """A name per entry of the vector features, from the env the data was recorded in (built without cameras)."""
    from dust_rl.envs.env import environment_state_names
    from dust_rl.envs.factory import make_env

    env = make_env(meta["env_id"], {**meta["env_kwargs"], "task": tasks[0], "obs_mode": "state"})
    state, action = env.unwrapped.state_names(), env.unwrapped.action_names()
    env.close()
    width = env_state.type.list_size if pa.types.is_fixed_size_list(env_state.type) else 1
    return {"observation.state": state, "observation.environment_state": environment_state_names(width),
            "action": action, EXPERT_ACTION_KEY: action}


def _feature(column: pa.Array, names: list[str] | None) -> dict:
    """LeRobot feature entry of a column: vectors have shape ``[D]`` and a name per entry, scalars shape ``[1]``
    and no names (as LeRobot's own index columns)."""
    if pa.types.is_fixed_size_list(column.type):
        return {"dtype": _DTYPES[column.type.value_type], "shape": [column.type.list_size], "names": names}
    return {"dtype": _DTYPES[column.type], "shape": [1], "names": None}


def _video_feature(image_shape: list[int], fps: int) -> dict:
    height, width, channels = image_shape
    return {"dtype": "video", "shape": [height, width, channels], "names": ["height", "width", "channels"],
            "info": {"video.height": height, "video.width": width, "video.codec": VIDEO_CODEC,
                     "video.pix_fmt": PIX_FMT, "video.is_depth_map": False, "video.fps": fps,
                     "video.channels": channels, "has_audio": False}}


def _episodes_table(meta: dict, video_keys: list[str], fps: int) -> pa.Table:
    episodes = meta["episodes"]
    starts = np.array([e["row_start"] for e in episodes], dtype=np.int64)
    ends = starts + np.array([e["length"] for e in episodes], dtype=np.int64)
    zeros = np.zeros(len(episodes), dtype=np.int64)
    columns = {
        "episode_index": pa.array([e["index"] for e in episodes], pa.int64()),
        "tasks": pa.array([[meta["instructions"][e["instruction_index"]]] for e in episodes]),
        "length": pa.array(ends - starts),
        "data/chunk_index": pa.array(zeros), "data/file_index": pa.array(zeros),
        "dataset_from_index": pa.array(starts), "dataset_to_index": pa.array(ends),
    }
    for key in video_keys:
        columns.update({f"videos/{key}/chunk_index": pa.array(zeros), f"videos/{key}/file_index": pa.array(zeros),
                        f"videos/{key}/from_timestamp": pa.array(starts / fps),
                        f"videos/{key}/to_timestamp": pa.array(ends / fps)})
    columns.update({"meta/episodes/chunk_index": pa.array(zeros), "meta/episodes/file_index": pa.array(zeros),
                    "dust_rl/task": pa.array([e["task"] for e in episodes]),
                    "dust_rl/seed": pa.array([e["seed"] for e in episodes], pa.int64()),
                    "dust_rl/success": pa.array([e["success"] for e in episodes])})
    return pa.table(columns)


def _tasks_table(instructions: list[str]) -> pa.Table:
    """Task strings as the pandas index (what ``pandas.read_parquet`` in LeRobot expects), plus ``task_index``."""
    table = pa.table({"task_index": pa.array(range(len(instructions)), pa.int64()),
                      "__index_level_0__": pa.array(instructions, pa.string())})
    pandas_meta = {
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                     "numpy_type": "int64", "metadata": None},
                    {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode",
                     "numpy_type": "object", "metadata": None}],
        "attributes": {}, "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0",
    }
    return table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)})


def _image_stats(data: TensorDictBase, cameras: list[str]) -> dict:
    """Per-channel statistics of pixel values in [0, 1] (shape ``[3, 1, 1]``), on at most 1000 evenly spaced frames."""
    rows = torch.linspace(0, data.shape[0] - 1, min(_IMAGE_STATS_FRAMES, data.shape[0])).long().unique()
    stats = {}
    for camera in cameras:
        pixels = data.get((*IMAGE_KEY, camera))[rows].double().div(255).transpose(0, 1).flatten(1)
        stats[IMAGE_PREFIX + camera] = {
            name: value.reshape(3, 1, 1).tolist() for name, value in (
                ("mean", pixels.mean(1)), ("std", pixels.std(1, correction=0)),
                ("min", pixels.min(1).values), ("max", pixels.max(1).values))}
        stats[IMAGE_PREFIX + camera]["count"] = [len(rows)]
    return stats


def _write_parquet(path: pathlib.Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)
