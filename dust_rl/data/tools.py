"""Looking at a dataset: a text summary and a grid video of its episodes."""

from __future__ import annotations

import pathlib
from collections.abc import Iterator, Sequence

import numpy as np

from dust_rl.errors import ConfigError
from dust_rl.keys import IMAGE_KEY

from .dataset import DemoDataset
from .video import write_mp4

# The largest side of a grid video: H.264's highest level (6.2) frames are 8192 px wide (libx264 refuses far wider).
MAX_VIDEO_SIDE = 8192


def folder_size(path: pathlib.Path) -> int:
    """Bytes of all files under ``path``."""
    return sum(file.stat().st_size for file in path.rglob("*") if file.is_file())


def dataset_summary(dataset: DemoDataset) -> str:
    """Episodes, tasks, lengths, success and sizes, as markdown."""
    meta, spec = dataset.meta, dataset.meta["spec"]
    data_bytes = folder_size(dataset.root / meta["data"])
    lines = [
        f"# {dataset.root}",
        f"- env: {meta['env_id']} {meta['env_kwargs']}"
        + (f" (imported from {meta['source']})" if meta.get("source") else "")
        + (f"; rollouts of {meta['policy']['file']} (sha256 {meta['policy']['sha256'][:12]})"
           if meta.get("policy") else ""),
        f"- episodes: {dataset.num_episodes}, transitions: {len(dataset)}, instructions: {len(dataset.instructions)}",
        f"- cameras: {', '.join(spec['cameras'])} at {spec['image_shape']}; state {spec['state_dim']}, "
        f"action {spec['action_dim']}; {spec['control_hz']:g} Hz",
        f"- seeds from {meta['start_seed']}; action noise std {meta['noise_std']}; "
        f"failed episodes kept: {meta['keep_failed']}",
        f"- size: {data_bytes / 2**20:.1f} MiB consolidated "
        f"({1000 * data_bytes / max(len(dataset), 1) / 2**20:.2f} MiB "
        f"per 1000 transitions), {folder_size(dataset.root) / 2**20:.1f} MiB in the folder",
        _caches_line(dataset),
        "",
        "| task | episodes | success | length mean | min | max |",
        "|---|---|---|---|---|---|",
    ]
    for task in dataset.tasks:
        episodes = [e for e in meta["episodes"] if e["task"] == task]
        lengths = np.array([e["length"] for e in episodes])
        success = np.mean([e["success"] for e in episodes]) if episodes else float("nan")
        lines.append(f"| {task} | {len(episodes)} | {100 * success:.0f}% | {lengths.mean():.1f} | "
                     f"{lengths.min()} | {lengths.max()} |" if episodes else f"| {task} | 0 | - | - | - | - |")
    return "\n".join(lines)


def _caches_line(dataset: DemoDataset) -> str:
    """The caches derived from the dataset (:mod:`dust_rl.storage.cache_files`), each with its size."""
    from dust_rl.storage.cache_files import cache_files

    files = cache_files(dataset.cache_root)
    listed = ", ".join(f"{path.relative_to(dataset.cache_root)} ({size / 2**20:.1f} MiB)" if size >= 2**20 else
                       f"{path.relative_to(dataset.cache_root)} ({size / 2**10:.0f} KiB)" for path, size in files)
    return f"- caches in {dataset.cache_root}: {listed or 'none'}"


def write_episode_grid(dataset: DemoDataset, out: str | pathlib.Path, episodes: Sequence[int] | None = None,
                       columns: int = 4, scale: int | None = None) -> pathlib.Path:
    """An MP4 playing episodes side by side (all cameras of an episode in one cell).

    Finished cells hold their last frame.

    Args:
        episodes: episode indices; defaults to the first 16.
        columns: cells per grid row (at most the episodes shown).
        scale: integer upscaling of the pixels; defaults to reaching at least 128 pixels per image.

    Raises:
        ConfigError: the grid would be more than :data:`MAX_VIDEO_SIDE` px high or wide.
    """
    episodes = list(episodes) if episodes is not None else list(range(min(16, dataset.num_episodes)))
    if not episodes:
        raise ValueError("no episodes to show")
    height, width = dataset.meta["spec"]["image_shape"][:2]
    scale = scale or max(1, -(-128 // height))
    columns = min(columns, len(episodes))  # more would only add blank cells
    cell = (height * scale, width * len(dataset.cameras) * scale)
    grid = (-(-len(episodes) // columns) * cell[0], columns * cell[1])
    if max(grid) > MAX_VIDEO_SIDE:  # checked before the file is opened: a frame that size takes minutes and GBs
        raise ConfigError(f"a grid of {len(episodes)} episodes in {columns} columns is {grid[0]}x{grid[1]} px, over "
                          f"the {MAX_VIDEO_SIDE} px a side H.264 takes; give at most {MAX_VIDEO_SIDE // cell[1]} "
                          f"--columns and {(MAX_VIDEO_SIDE // cell[0]) * (MAX_VIDEO_SIDE // cell[1])} --episodes")
    out = pathlib.Path(out)
    write_mp4(out, _grid_frames(dataset, episodes, columns, scale), dataset.meta["spec"]["fps"], pad_odd=True)
    return out


def _grid_frames(dataset: DemoDataset, episodes: list[int], columns: int, scale: int) -> Iterator[np.ndarray]:
    cells = [_cell_frames(dataset, index) for index in episodes]
    blank = np.zeros_like(cells[0][0])
    rows = -(-len(cells) // columns)
    for t in range(max(len(cell) for cell in cells)):
        tiles = [cell[min(t, len(cell) - 1)] for cell in cells] + [blank] * (rows * columns - len(cells))
        grid = np.concatenate([np.concatenate(tiles[r * columns:(r + 1) * columns], axis=1) for r in range(rows)])
        yield grid.repeat(scale, axis=0).repeat(scale, axis=1)


def _cell_frames(dataset: DemoDataset, index: int) -> np.ndarray:
    """Frames ``[T, H, W * cameras, 3]`` of one episode, cameras side by side."""
    rows = dataset.episode(index)
    images = [rows.get((*IMAGE_KEY, camera)).permute(0, 2, 3, 1).numpy() for camera in dataset.cameras]
    return np.concatenate(images, axis=2)
