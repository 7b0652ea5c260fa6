"""``dust-rl bench suite`` on a tiny budget: every cell runs once, the tables come out, a rerun redoes nothing."""

from __future__ import annotations

import dataclasses
import json

import pytest
from test_train import TINY_POLICY

from dust_rl.agents import PolicyConfig, load_policy, save_image_encoder
from dust_rl.bench.suite import AS_TRAINED, VISION_AS_NOISE, WITH_VIDEO, Cell, SuiteConfig, markdown, plan, run_suite
from dust_rl.errors import ConfigError
from dust_rl.train.imitation import TrainSettings
from dust_rl.train.settings import LoggingSettings, OptimSettings, RuntimeSettings

pytestmark = pytest.mark.usefixtures("one_thread")


def test_suite_runs_every_cell_once_writes_the_tables_and_resumes(tiny_encoder, tmp_path, capsys):
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    train = TrainSettings(policy=PolicyConfig(**TINY_POLICY, image_encoder=str(encoder)),
                          optim=OptimSettings(steps=2, batch_size=8),
                          logging=LoggingSettings(log_every=1, checkpoint_every=2),
                          runtime=RuntimeSettings(threads=1, progress=False))
    config = SuiteConfig(out=tmp_path / "suite", task="press_button", demos=(1, 2), variants=("dust", "action_only"),
                         seeds=(0,), train=train, vision_steps=(4, 8), eval_episodes=1, image_size=32, max_steps=6,
                         video_dataset=tmp_path / "suite" / "data" / "1", progress=False)  # collected by the suite
    results = run_suite(config, "dust-rl bench suite ...")
    assert "budget: collect 2 demonstrations x 1 tasks; train 5 policies x 2 steps" in capsys.readouterr().out
    rows = {(r["variant"], r["demos"], r["sampler"]): r for r in results["rows"]}
    assert set(rows) == {("dust", 2, AS_TRAINED), ("action_only", 2, AS_TRAINED),
                         ("dust", 2, "async N_A=4 N_o=4"), ("dust", 2, "sync N_A=N_o=4"),
                         ("dust", 2, "async N_A=4 N_o=8"), ("dust", 2, "sync N_A=N_o=8"),
                         ("dust", 2, VISION_AS_NOISE),
                         ("dust", 1, AS_TRAINED), ("action_only", 1, AS_TRAINED), (WITH_VIDEO, 2, AS_TRAINED)}
    assert all(r["episodes"] == 1 and 0 <= r["ci95_low"] <= r["ci95_high"] <= 1 for r in rows.values())
    assert rows["dust", 2, AS_TRAINED]["trainable_parameters"] > rows["action_only", 2, AS_TRAINED][
        "trainable_parameters"]
    sync8 = json.loads((tmp_path / "suite" / "eval" / "dust_seed0_demos2" / "sync_N_AN_o8" / "report.json").read_text())
    assert sync8["sampler"] == {"name": "sync", "n_action_steps": 8, "vision_steps": 8, "candidates": 1,
                                "noise_scale": 1.0}
    noise = json.loads((tmp_path / "suite" / "eval" / "dust_seed0_demos2" / "vision_as_noise_N_A4" /
                        "report.json").read_text())
    assert noise["sampler"]["name"] == "action_only"
    markdown = (tmp_path / "suite" / "results.md").read_text()
    assert "## Data scaling" in markdown and "| action_only | 1 | as trained |" in markdown
    assert f"| {WITH_VIDEO} | 2 | as trained |" in markdown
    video_policy = tmp_path / "suite" / "train" / "dust_video_seed0_demos2" / "policy.pt"
    assert load_policy(video_policy).info["video_dataset"] == str(config.video_dataset)
    assert (tmp_path / "suite" / "results.png").read_bytes()[:4] == b"\x89PNG"

    # A rerun finds every cell on disk: no training, no evaluation.
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "suite").rglob("*") if p.name in ("policy.pt",
                                                                                            "report.json")}
    assert len(stamps) == 5 + len(rows)
    assert run_suite(config)["rows"] == results["rows"]
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())

    # Cells on disk from other settings are refused, not passed off as this study's.
    longer_train = dataclasses.replace(train, optim=dataclasses.replace(train.optim, steps=3))
    longer = dataclasses.replace(config, train=longer_train)
    with pytest.raises(ConfigError, match="other settings"):
        run_suite(longer)
    with pytest.raises(ConfigError, match="holds an evaluation of seeds"):
        run_suite(dataclasses.replace(config, eval_episodes=2))
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())


def test_suite_settings_are_checked():
    with pytest.raises(ConfigError, match="multiples of N_A = 4"):
        SuiteConfig(vision_steps=(4, 6))
    with pytest.raises(ConfigError, match="at least one value"):
        SuiteConfig(seeds=())
    with pytest.raises(ConfigError, match="would train nothing"):
        SuiteConfig(variants=())


def test_no_variants_with_a_video_dataset_plans_only_the_action_free_row(tmp_path):
    config = SuiteConfig(variants=(), seeds=(0, 1), demos=(50, 200), video_dataset=tmp_path)
    assert plan(config) == [(Cell("dust", 0, 200, video=True), AS_TRAINED), (Cell("dust", 1, 200, video=True),
                                                                            AS_TRAINED)]


def test_the_tables_leave_out_parts_the_study_did_not_run():
    row = {"variant": "joint", "demos": 200, "sampler": AS_TRAINED, "trainable_parameters": 2e6, "success_rate": 0.8,
           "successes": 40, "episodes": 50, "ci95_low": 0.67, "ci95_high": 0.89, "per_seed": [0.8]}
    text = markdown({"task": "press_button", "env": "DustFranka-v0", "eval_seeds": [10000, 10049], "main_demos": 200,
                     "rows": [row, {**row, "variant": "action_only"}]}, None)
    assert "| joint | 200 | as trained | 2.00M | 80% (40/50) | 67-89% | 80% |" in text
    assert "## Variants" in text and "## Data scaling" not in text and "## DUST's samplers" not in text
