"""Closed-loop evaluation: Wilson intervals, report files, videos, determinism across runs and workers, bad input."""

from __future__ import annotations

import dataclasses
import json
import pathlib

import numpy as np
import pytest
from tqdm import tqdm

from dust_rl.agents import (
    AutoencoderConfig,
    ConvAutoencoder,
    SamplerConfig,
    load_policy,
    make_policy,
    save_policy,
)
from dust_rl.agents.execution import replans
from dust_rl.agents.factory import POLICY_KIND
from dust_rl.data.video import read_mp4, write_mp4
from dust_rl.errors import CheckpointError, ConfigError
from dust_rl.evaluate.closed_loop import EvalConfig, eval_collector, evaluate, prepare, run_task
from dust_rl.evaluate.records import Episode, paired_comparison, wilson_interval
from dust_rl.evaluate.report import plot_loss_curves, read_scalar_csv
from dust_rl.evaluate.resampling import describe_sampler
from dust_rl.evaluate.video import LABEL_HEIGHT, future_decoder
from dust_rl.keys import ACTION_CHUNK_KEY
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

IMAGE = 32
QUIET = RuntimeSettings(threads=1, progress=False)  # dust-rl eval's one thread per worker, no progress bars
SIZES = dict(horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=1, state_dim=17)
INFO = {"env_id": "DustFranka-v0", "env_kwargs": {"image_size": IMAGE}, "tasks": ["press_button"],
        "image_size": [IMAGE, IMAGE]}


def tiny_policy_file(path: pathlib.Path, text_encoder, info: dict | None = None, **sizes) -> pathlib.Path:
    """An untrained tiny policy for 32 px front + wrist cameras (the conftest ``tiny_encoder`` shape)."""
    encoder = ConvAutoencoder(AutoencoderConfig(image_size=IMAGE, dim=16, width=8, max_width=16))
    policy = make_policy("dust", image_encoder=encoder, text_encoder=text_encoder, cameras=["front", "wrist"],
                         **{**SIZES, "action_dim": 7, **sizes})
    policy.info = INFO if info is None else info
    return save_policy(policy, path)


def write_loss_logs(train_dir: pathlib.Path) -> None:
    """CSVLogger files of a training run that was resumed: steps 2 and 3 are logged twice."""
    scalars = train_dir / "logs" / "run" / "scalars" / "train"
    scalars.mkdir(parents=True)
    (scalars / "loss.csv").write_text("0,2.0\n1,1.5\n2,1.2\n3,1.1\n2,1.0\n3,0.9\n4,0.8\n")
    (scalars / "loss_action.csv").write_text("0,1.0\n2,0.5\n4,0.3\n")
    (scalars / "lr.csv").write_text("0,0.001\n")


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory, minilm) -> pathlib.Path:
    root = tmp_path_factory.mktemp("trained")
    write_loss_logs(root)
    return tiny_policy_file(root / "policy.pt", minilm)


@pytest.fixture(scope="module")
def eval_config(policy_path, tmp_path_factory) -> EvalConfig:
    return EvalConfig(policy=policy_path, out=tmp_path_factory.mktemp("eval"), episodes=2, workers=1, max_steps=10,
                      videos=1, runtime=QUIET)


@pytest.fixture(scope="module")
def report(eval_config) -> dict:
    return evaluate(eval_config, command="dust-rl eval --policy policy.pt")


def test_paired_comparison_counts_discordant_episodes_and_tests_them_exactly():
    def run(outcomes):
        return [Episode(seed, bool(won), 10, "") for seed, won in enumerate(outcomes)]

    base = run([0, 0, 0, 0, 0, 0, 1, 1])
    assert paired_comparison(base, base) == {"gained": 0, "lost": 0, "p_value": 1.0}
    six_gained = paired_comparison(base, run([1, 1, 1, 1, 1, 1, 1, 1]))
    assert six_gained == {"gained": 6, "lost": 0, "p_value": pytest.approx(2 / 2 ** 6)}
    # One each way: the binomial tail P(X <= 1 | n = 2) = 3/4, doubled and capped at 1.
    assert paired_comparison(base, run([1, 0, 0, 0, 0, 0, 0, 1]))["p_value"] == 1.0
    with pytest.raises(ValueError, match="same seeds"):
        paired_comparison(base, run([1, 1]))


def test_wilson_interval_known_values():
    assert wilson_interval(0, 20) == pytest.approx((0.0, 0.1611), abs=1e-4)
    assert wilson_interval(20, 20) == pytest.approx((0.8389, 1.0), abs=1e-4)
    assert wilson_interval(10, 20) == pytest.approx((0.2993, 0.7007), abs=1e-4)
    assert wilson_interval(1, 1, z=0.0) == (1.0, 1.0)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    for n in range(1, 200):  # the interval holds the rate itself (rounding put 100/100's upper end at 1 - 1e-16)
        assert wilson_interval(0, n)[0] == 0.0 and wilson_interval(n, n)[1] == 1.0


def test_report_rows_count_each_seed_once(report, eval_config):
    assert json.loads((eval_config.out / "report.json").read_text()) == report
    (row,) = report["tasks"]
    seeds = [eval_config.seed, eval_config.seed + 1]
    assert row["task"] == "press_button" and row["episodes"] == 2 and row["seeds"] == seeds
    episodes = [Episode.from_json(e) for e in row["per_episode"]]
    assert [e.seed for e in episodes] == seeds
    assert all(1 <= e.length <= 10 for e in episodes)  # max_steps
    assert row["successes"] == sum(e.success for e in episodes)
    assert (row["ci95_low"], row["ci95_high"]) == wilson_interval(row["successes"], 2)
    assert row["mean_length"] == sum(e.length for e in episodes) / 2
    assert report["overall"]["episodes"] == 2 and report["overall"]["successes"] == row["successes"]
    assert report["env_steps"] == sum(e.length for e in episodes) and report["env_steps_per_s"] > 0
    assert report["sampler"] == {"name": "async", "n_action_steps": 4, "vision_steps": 4, "noise_scale": 1.0}
    assert report["variant"] == "dust" and report["env_id"] == "DustFranka-v0"
    policy = load_policy(eval_config.policy)
    assert report["trainable_parameters"] == sum(p.numel() for p in policy.parameters() if p.requires_grad) > 0
    assert report["env_kwargs"] == {"image_size": IMAGE, "max_episode_steps": 10}


def test_report_files(report, eval_config):
    markdown = (eval_config.out / "report.md").read_text()
    assert "| task | episodes | success | 95% CI | mean length |" in markdown
    assert "| press_button | 2 |" in markdown and "**overall**" in markdown
    assert "dust-rl eval --policy policy.pt" in markdown and "N_A = 4, N_o = 4" in markdown
    assert f"{report['trainable_parameters'] / 1e6:.2f}M trainable parameters" in markdown
    for png in ("success.png", "loss.png"):
        assert (eval_config.out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert pathlib.Path(report["loss_plot"]) == eval_config.out / "loss.png"


def test_video_is_the_evaluated_episode_with_its_predicted_future(report, eval_config):
    (row,) = report["tasks"]
    (video,) = row["videos"]
    assert video["seed"] == eval_config.seed
    # Same seed, same re-planning and sampling noise: the recorded episode is the evaluated one, bit for bit.
    assert {key: video[key] for key in ("seed", "success", "length", "digest")} == row["per_episode"][0]
    frames = list(read_mp4(pathlib.Path(video["path"])))
    assert len(frames) == video["length"] + 1  # every observation, the last one included
    assert frames[0].shape == (LABEL_HEIGHT + IMAGE, 4 * IMAGE, 3)  # front | wrist | prediction | real future


def test_a_video_is_replaced_only_once_the_new_one_is_whole(tmp_path):
    path = tmp_path / "episode.mp4"  # an earlier evaluation's video
    write_mp4(path, [np.full((32, 32, 3), 90, np.uint8)] * 4, fps=20)
    before = path.read_bytes()

    def interrupted():
        yield from [np.zeros((32, 32, 3), np.uint8)] * 100  # enough for the encoder to write packets
        raise KeyboardInterrupt  # the re-run stopped while it renders

    with pytest.raises(KeyboardInterrupt):
        write_mp4(path, interrupted(), fps=20)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["episode.mp4"]
    assert write_mp4(path, [np.zeros((32, 32, 3), np.uint8)] * 3, fps=20) == 3 and len(list(read_mp4(path))) == 3


def test_same_config_same_episodes_with_any_worker_count(report, eval_config, tmp_path):
    again = evaluate(dataclasses.replace(eval_config, out=tmp_path / "again", videos=0))
    assert again["tasks"][0]["per_episode"] == report["tasks"][0]["per_episode"]
    two_workers = evaluate(dataclasses.replace(eval_config, out=tmp_path / "two", videos=0, workers=2))
    assert two_workers["tasks"][0]["per_episode"] == report["tasks"][0]["per_episode"]
    assert not list((tmp_path / "two").glob("videos/*"))


def test_missing_or_corrupt_policy_file(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint file"):
        evaluate(EvalConfig(policy=tmp_path / "missing.pt", out=tmp_path))
    (tmp_path / "garbage.pt").write_bytes(b"\x00not a checkpoint" * 64)
    with pytest.raises(CheckpointError, match="corrupt"):
        evaluate(EvalConfig(policy=tmp_path / "garbage.pt", out=tmp_path))


def test_policy_for_another_action_space(tmp_path, minilm):
    path = tiny_policy_file(tmp_path / "policy.pt", minilm, action_dim=3)
    with pytest.raises(CheckpointError, match="action_dim: policy has 3, env has 7"):
        evaluate(EvalConfig(policy=path, out=tmp_path / "eval"))


def test_a_policy_for_other_frames_or_cameras_is_refused(tmp_path, minilm):
    # Trained on 32 px frames (as recorded at training), its info edited to ask for a 64 px env.
    claims_64 = tiny_policy_file(tmp_path / "claims_64.pt", minilm,
                                 info={**INFO, "env_kwargs": {"image_size": 64}, "image_size": [32, 32]})
    config = EvalConfig(policy=claims_64, out=tmp_path / "eval", episodes=1, max_steps=5, runtime=QUIET)
    with pytest.raises(CheckpointError, match=r"image size: policy was trained on \[32, 32\] px frames, env renders "
                                              r"\[64, 64\]"):
        evaluate(config)
    path = save_policy(load_policy(claims_64), tmp_path / "other_camera.pt")
    payload = load_checkpoint(path, POLICY_KIND)
    payload["cameras"], payload["info"] = ["front", "belly"], INFO
    save_checkpoint(payload, path, POLICY_KIND)
    with pytest.raises(CheckpointError, match=r"cameras: policy reads \['belly'\]"):
        evaluate(dataclasses.replace(config, policy=path))
    unrecorded = tiny_policy_file(tmp_path / "unrecorded.pt", minilm,  # an older file, or one edited to run at 64 px
                                  info={**INFO, "env_kwargs": {"image_size": 64}, "image_size": None})
    with pytest.raises(CheckpointError, match="policy records no frame size it was trained on"):
        evaluate(dataclasses.replace(config, policy=unrecorded))
    assert not (tmp_path / "eval").exists()


def test_bad_tasks_and_sampler_settings_fail_before_any_episode(policy_path, tmp_path, minilm):
    config = EvalConfig(policy=policy_path, out=tmp_path / "eval")
    with pytest.raises(ConfigError, match="unknown franka task 'fly'.*press_button"):
        evaluate(dataclasses.replace(config, tasks=("press_button", "fly")))
    with pytest.raises(ConfigError, match="async sampler only"):
        evaluate(dataclasses.replace(config, sampling=SamplerConfig("sync", vision_step_ratio=2)))
    with pytest.raises(ConfigError, match="episodes must be >= 1"):
        evaluate(dataclasses.replace(config, episodes=0))
    bare = tiny_policy_file(tmp_path / "bare.pt", minilm, info={})
    with pytest.raises(ConfigError, match="give --env and --tasks"):
        evaluate(EvalConfig(policy=bare, out=tmp_path / "eval"))
    assert not (tmp_path / "eval").exists()


def test_sampler_description_counts_vision_steps():
    assert describe_sampler(SamplerConfig("async", 4, 2)) == {"name": "async", "n_action_steps": 4, "vision_steps": 8,
                                                              "noise_scale": 1.0}
    assert describe_sampler(SamplerConfig("sync", 4))["vision_steps"] == 4
    assert describe_sampler(SamplerConfig("action_only", 4))["vision_steps"] == 0


def test_no_predicted_future_without_a_prediction_or_a_decoder(policy_path):
    policy = load_policy(policy_path)
    assert future_decoder(policy) is not None
    policy.set_sampler(SamplerConfig("action_only"))
    assert future_decoder(policy) is None


def test_loss_curves_keep_the_last_value_of_a_repeated_step(tmp_path):
    write_loss_logs(tmp_path / "run")
    scalars = tmp_path / "run" / "logs" / "run" / "scalars"
    assert read_scalar_csv(scalars / "train" / "loss.csv") == ([0, 1, 2, 3, 4], [2.0, 1.5, 1.0, 0.9, 0.8])
    for source in (tmp_path / "run", scalars):
        out = plot_loss_curves(source, tmp_path / f"{source.name}.png")
        assert out is not None and out.read_bytes()[:4] == b"\x89PNG"
    assert plot_loss_curves(tmp_path / "empty", tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_the_executor_samples_a_chunk_where_the_replanning_rule_says(policy_path, tmp_path):
    config = EvalConfig(policy=policy_path, out=tmp_path, episodes=1, workers=1, max_steps=10, videos=0,
                        execute_steps=4, runtime=QUIET)
    policy, setup = prepare(config)
    with eval_collector(setup, "press_button", policy, config.worker_pool(), config.seed) as collector:
        (episode,), kept = run_task(collector, range(config.seed, config.seed + 1), tqdm(disable=True), keep=1)
    chunks = kept[episode.seed].get(ACTION_CHUNK_KEY)
    sampled = [t == 0 or not chunks[t].equal(chunks[t - 1]) for t in range(episode.length)]
    assert sampled == [replans(t, 4) for t in range(episode.length)] and sum(sampled) == 3  # steps 0, 4 and 8
