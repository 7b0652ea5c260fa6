"""``dust-rl demo``: the scripted expert's episodes as one MP4 per task, through the project's one video writer."""

from __future__ import annotations

import json

import pytest

from dust_rl.cli import main
from dust_rl.data.video import read_mp4

pytestmark = pytest.mark.usefixtures("one_thread")


def test_demo_writes_a_video_even_at_an_odd_image_size(tmp_path, capsys):
    main(["demo", "--task", "press_button", "--episodes", "1", "--image-size", "33", "--out", str(tmp_path)])
    (row,) = json.loads((tmp_path / "summary.json").read_text())
    frames = list(read_mp4(tmp_path / "press_button.mp4"))
    assert row["successes"] == 1 and len(frames) > 1
    assert frames[0].shape == (34, 66, 3)  # front | wrist, 33 rows padded by one repeated row for H.264
    assert "press_button: 1/1 successful" in capsys.readouterr().out


def test_expert_table_counts_episodes_as_collect_and_eval_do(tmp_path, capsys):
    main(["expert-table", "--task", "press_button", "--episodes", "2", "--out", str(tmp_path / "table")])
    (row,) = json.loads((tmp_path / "table.json").read_text())
    assert row["task"] == "press_button" and row["episodes"] == 2
    assert "| press_button |" in capsys.readouterr().out
