"""Damaged or mismatched datasets fail with a DatasetError that names the problem."""

from __future__ import annotations

import json
import shutil

import gymnasium as gym
import pytest

from dust_rl.cli import main
from dust_rl.data import DatasetError, DemoDataset, collect_demos
from dust_rl.data.tools import dataset_summary


@pytest.fixture
def copy(demo_dir, tmp_path):
    target = tmp_path / "ds"
    shutil.copytree(demo_dir, target)
    return target


def _data_dir(root):
    return root / json.loads((root / "meta.json").read_text())["data"]


def test_truncated_data_file(copy):
    image = _data_dir(copy) / "observation" / "image" / "front.memmap"
    image.write_bytes(image.read_bytes()[:1000])
    with pytest.raises(DatasetError, match=r"front\.memmap: truncated"):
        DemoDataset(copy)


def test_missing_data_file(copy):
    (_data_dir(copy) / "action.memmap").unlink()
    with pytest.raises(DatasetError, match=r"action\.memmap: missing"):
        DemoDataset(copy)


def test_missing_or_corrupt_metadata(copy, tmp_path):
    with pytest.raises(DatasetError, match="not a dust-rl dataset"):
        DemoDataset(tmp_path / "nowhere")
    (copy / "meta.json").write_text('{"format_version": 1, "data": "data-')
    with pytest.raises(DatasetError, match=r"meta\.json: unreadable"):
        DemoDataset(copy)


def test_newer_format_version(copy):
    meta = json.loads((copy / "meta.json").read_text())
    (copy / "meta.json").write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(DatasetError, match="format version 99"):
        DemoDataset(copy)


def test_row_count_disagrees_with_episode_table(copy):
    meta = json.loads((copy / "meta.json").read_text())
    meta["episodes"][-1]["length"] += 1
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="rows on disk"):
        DemoDataset(copy)


@pytest.mark.parametrize("field,value", [("length", -3), ("length", 0), ("row_start", 5), ("instruction_index", 99),
                                         ("task", "fly_to_moon")])
def test_garbled_episode_table(copy, field, value):
    meta = json.loads((copy / "meta.json").read_text())
    meta["episodes"][1][field] = value
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"meta\.json: episode 1 is garbled"):
        DemoDataset(copy)


def test_dataset_does_not_match_requested_env(copy):
    env = gym.make("DustFranka-v0", task="press_button", image_size=48, cameras=["front"])
    with pytest.raises(DatasetError, match=r"image_shape: dataset has \[32, 32, 3\], env has \[48, 48, 3\]") as info:
        DemoDataset(copy, env=env)
    assert "cameras" in str(info.value)
    env.close()
    DemoDataset(copy, env=gym.make("DustFranka-v0", task="open_drawer", image_size=32))  # a matching env passes


def test_corrupt_episode_record_blocks_resume(copy):
    record = next((copy / "episodes" / "press_button").glob("seed-*/episode.json"))
    record.write_text("{")
    with pytest.raises(DatasetError, match="unreadable episode record"):
        collect_demos(copy, tasks=["press_button"], episodes=3, env_kwargs={"image_size": 32}, progress=False)


def test_cli_reports_errors_without_traceback(copy, capsys):
    (copy / "meta.json").unlink()
    with pytest.raises(SystemExit, match="dust-rl: error: .*no meta.json"):
        main(["dataset", "info", str(copy)])


def test_info_and_video_tools(demo_dir, tmp_path, capsys):
    main(["dataset", "info", str(demo_dir)])
    out = capsys.readouterr().out
    assert "| press_button | 3 | 100% |" in out and "| open_drawer | 3 | 100% |" in out
    assert out == dataset_summary(DemoDataset(demo_dir)) + "\n"
    main(["dataset", "video", str(demo_dir), "--out", str(tmp_path / "grid.mp4"), "--episodes", "6", "--columns", "3"])
    from dust_rl.data.video import read_mp4

    frames = list(read_mp4(tmp_path / "grid.mp4"))
    longest = max(e["length"] for e in DemoDataset(demo_dir).meta["episodes"])
    assert len(frames) == longest and frames[0].shape == (2 * 32 * 4, 3 * 2 * 32 * 4, 3)


def test_a_video_grid_wider_than_h264_takes_is_refused_before_a_file_is_made(demo_dir, tmp_path):
    """More columns than episodes used to widen the grid with blank cells until libx264 refused it (1000 columns) or
    the first frame took gigabytes (100,000 columns, a hang leaving a temp file)."""
    from dust_rl.data.tools import MAX_VIDEO_SIDE, write_episode_grid
    from dust_rl.data.video import read_mp4
    from dust_rl.errors import ConfigError

    main(["dataset", "video", str(demo_dir), "--out", str(tmp_path / "grid.mp4"), "--episodes", "2", "--columns",
          "1000"])
    assert next(read_mp4(tmp_path / "grid.mp4")).shape == (32 * 4, 2 * 2 * 32 * 4, 3)  # the two episodes' cells only
    cell_width = 2 * 32 * 4  # front | wrist at scale 4
    many = [0] * (MAX_VIDEO_SIDE // cell_width + 1)
    with pytest.raises(ConfigError, match=rf"is 128x{len(many) * cell_width} px, over the {MAX_VIDEO_SIDE} px a side "
                                          rf"H.264 takes; give at most {MAX_VIDEO_SIDE // cell_width} --columns"):
        write_episode_grid(DemoDataset(demo_dir), tmp_path / "wide.mp4", many, columns=len(many))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid.mp4"]  # nothing half written, no temp file
