"""The main job end to end on a tiny setting: collect 2 episodes, train a few steps, evaluate, report."""

from __future__ import annotations

import json

import pytest

from dust_rl.agents import save_image_encoder
from dust_rl.cli import main

pytestmark = pytest.mark.usefixtures("one_thread")


def test_quickstart_then_eval_command(tiny_encoder, tmp_path, capsys):
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    out = tmp_path / "qs"
    args = ["quickstart", "--out", str(out), "--task", "press_button", "--demos", "2", "--train.optim.steps", "4",
            "--train.optim.batch-size", "8", "--eval-episodes", "1", "--image-size", "32",
            "--train.model.image-encoder", str(encoder), "--train.model.cond-grid", "4", "4",
            "--train.model.readout-grid", "4", "4", "--train.readout.aux-frames", "8",
            "--train.readout.warmup-steps", "2", "--runtime.threads", "1", "--runtime.no-progress"]
    main(args)
    printed = capsys.readouterr().out
    assert "press_button: " in printed and str(out / "eval" / "report.md") in printed

    report = json.loads((out / "eval" / "report.json").read_text())
    (row,) = report["tasks"]
    assert row["task"] == "press_button" and row["episodes"] == 1 and 0 <= row["ci95_low"] <= row["ci95_high"] <= 1
    assert report["command"].startswith("dust-rl quickstart --out")
    markdown = (out / "eval" / "report.md").read_text()
    assert "| press_button | 1 |" in markdown
    for name in ("success.png", "loss.png", f"videos/press_button_seed{report['seeds'][0]}.mp4"):
        assert (out / "eval" / name).stat().st_size > 0, name
    summary = json.loads((out / "quickstart.json").read_text())
    assert set(summary["stages_seconds"]) == {"collect", "train", "eval", "total"}
    # The default recipe (not given above) trained: the token read-out, fitted first on rendered frames.
    policy = summary["quickstart"]["train"]["policy"]
    assert policy["readout"] == "tokens" and policy["text_fusion"] and policy["aux_state_input"]
    assert (out / "train" / "logs" / "train" / "scalars" / "warmup" / "loss_aux_frames.csv").stat().st_size > 0

    # Re-running resumes: the data and the finished training are reused, only evaluation runs again.
    logged = (out / "train" / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text()
    meta = (out / "data" / "meta.json").read_text()
    main(args)
    assert (out / "train" / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text() == logged
    assert (out / "data" / "meta.json").read_text() == meta

    main(["eval", "--policy", str(out / "train" / "policy.pt"), "--out", str(tmp_path / "eval"), "--episodes", "1",
          "--workers", "1", "--max-steps", "5", "--videos", "0", "--runtime.no-progress"])
    assert "overall: " in capsys.readouterr().out
    assert json.loads((tmp_path / "eval" / "report.json").read_text())["tasks"][0]["mean_length"] <= 5
