"""``dust-rl diagnose world-model`` and the sampler's vision source it is built on."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from conftest import make_tiny_encoder

from dust_rl.agents import DustConfig, DustModel, SamplerConfig, random_batch
from dust_rl.agents.model.samplers import action_only_schedule, async_schedule, run_schedule
from dust_rl.cli import main
from dust_rl.data import DatasetError, collect_demos
from dust_rl.diagnose.world_model import WorldModelDiagnosis, diagnose
from dust_rl.errors import ConfigError
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.settings import LoggingSettings, OptimSettings, TrainRuntime

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = {"horizon": 4, "d_model": 32, "n_heads": 2, "n_mmdit": 2, "n_dit": 0}


def _model_and_context(**config):
    """A model with every weight random (a new one's zero-initialised gates and decoders output zero velocity,
    which no input could change) and a chunk context."""
    torch.manual_seed(0)
    model = DustModel(DustConfig(**{**TINY, **config})).eval()
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.normal_(0.0, 0.3)
    batch = random_batch(model.config, 3, 5, torch.Generator().manual_seed(1))
    return model, model.encode_context(batch["state"], batch["cond_tokens"])


def _drawn_noise(model, seed: int = 0):
    """The action and vision noise ``run_schedule`` draws from a generator seeded ``seed``, in its order."""
    generator, cfg = torch.Generator().manual_seed(seed), model.config
    action = torch.randn(3, cfg.horizon, cfg.action_dim, generator=generator)
    return action, torch.randn(3, cfg.n_vision_tokens, cfg.vision_dim, generator=generator)


def test_a_noise_source_turns_the_joint_sampler_into_the_action_only_one():
    """With the vision stream held at its initial noise and tau_o = 0, the synchronous schedule steps the actions
    exactly as the action-only schedule does: the source replaces the vision input and nothing else."""
    model, ctx = _model_and_context()
    _, noise = _drawn_noise(model)
    held, vision = run_schedule(model, ctx, async_schedule(4, 1), torch.Generator().manual_seed(0),
                                vision_source=lambda step: (noise, 0.0))
    reference, _ = run_schedule(model, ctx, action_only_schedule(4), torch.Generator().manual_seed(0))
    assert torch.equal(held, reference)
    assert torch.equal(vision, noise)


def test_the_vision_source_reaches_the_actions():
    model, ctx = _model_and_context()
    future = torch.randn(3, model.config.n_vision_tokens, model.config.vision_dim)
    seen = []

    def source(step):
        seen.append(step.tau_o)
        return future * step.tau_o, step.tau_o

    oracle, vision = run_schedule(model, ctx, async_schedule(2, 2), torch.Generator().manual_seed(0),
                                  vision_source=source)
    own, _ = run_schedule(model, ctx, async_schedule(2, 2), torch.Generator().manual_seed(0))
    assert seen == [step.tau_o for step in async_schedule(2, 2)]
    assert torch.equal(vision, future * seen[-1])
    assert not torch.allclose(oracle, own)  # the joint attention reads the vision tokens


def test_a_given_future_evaluates_the_model_only_where_the_actions_move():
    """Under the async schedule with q > 1, a step that only moves the vision stream has nothing to compute once
    the vision tokens are given (a trunk with DiT blocks used to fail on the empty step)."""
    model, ctx = _model_and_context(n_dit=1)
    future = torch.randn(3, model.config.n_vision_tokens, model.config.vision_dim)
    calls = []
    hook = model.register_forward_hook(lambda module, args, out: calls.append(args[3][0].item()))
    try:
        run_schedule(model, ctx, async_schedule(2, 2), torch.Generator().manual_seed(0),
                     vision_source=lambda step: (future, step.tau_o))
    finally:
        hook.remove()
    assert calls == [step.tau_a for step in async_schedule(2, 2) if step.dt_a]


@pytest.fixture(scope="module")
def trained(demo_dir, tmp_path_factory):
    """A tiny DUST policy trained on a copy of the demo dataset, and another copy as held-out episodes."""
    from dust_rl.agents import PolicyConfig, save_image_encoder

    root = tmp_path_factory.mktemp("diagnose")
    data = shutil.copytree(demo_dir, root / "data")
    encoder = save_image_encoder(make_tiny_encoder(), root / "encoder.pt")
    policies = {}
    for variant in ("dust", "action_only"):
        config = TrainConfig(dataset=data, out=root / variant, optim=OptimSettings(steps=6, batch_size=8),
                             logging=LoggingSettings(checkpoint_every=6, loggers=("csv",)),
                             runtime=TrainRuntime(threads=1, progress=False),
                             policy=PolicyConfig(**TINY, variant=variant, image_encoder=str(encoder)))
        policies[variant] = train(config).policy
    return policies, data, shutil.copytree(demo_dir, root / "heldout")


def test_report_of_a_dust_policy(trained, tmp_path, capsys):
    policies, _, heldout = trained
    out = tmp_path / "report"
    main(["diagnose", "world-model", "--policy", str(policies["dust"]), "--dataset", str(heldout), "--out",
          str(out), "--windows", "48", "--batch-size", "16", "--runtime.no-progress", "--runtime.threads", "1"])
    report = json.loads((out / "report.json").read_text())
    assert set(report["oracle_future"]["conditions"]) == {"own", "true", "present", "noise", "other"}
    assert {"true - noise", "true - present"} <= set(report["oracle_future"]["paired_action_error"])
    buckets = report["vision_stream"]["buckets"]
    assert len(buckets) == 5 and all(row["windows"] == buckets[0]["windows"] > 0 for row in buckets)
    assert buckets[0]["episodes"] > 1
    # Near tau_o = 1 the one-step estimate is the noised target itself, whatever the stream predicts.
    assert buckets[-1]["mean"] < buckets[0]["mean"]
    assert (out / "world_model.png").stat().st_size > 0
    assert report["futures"] == {"figure": str(out / "futures.png"), "token_decoder": None}  # the encoder decodes
    printed = capsys.readouterr().out
    assert "The oracle-future test" in printed and f"predicted futures: {out / 'futures.png'}" in printed
    # Two tasks: each reading per task too, and the episodes split between them (the mean over all episodes is
    # their episode-weighted mean).
    per_task, overall = report["oracle_future"]["per_task"], report["oracle_future"]["conditions"]
    assert len(per_task) == 2 and set(report["vision_stream"]["per_task"]) == set(per_task)
    def split_between_tasks(rows: list[dict], whole: dict) -> None:
        assert sum(row["windows"] for row in rows) == whole["windows"]
        assert sum(row["episodes"] * row["mean"] for row in rows) / sum(row["episodes"] for row in rows) == (
            pytest.approx(whole["mean"], rel=1e-12))

    for condition in overall:
        split_between_tasks([task["action_error"][condition] for task in per_task.values()],
                            overall[condition]["action_error"])
    split_between_tasks([task["joint_sample"] for task in report["vision_stream"]["per_task"].values()],
                        report["vision_stream"]["joint_sample"])  # of the windows whose t+H is inside the episode
    assert all(set(task["paired_action_error"]) == {"true - noise", "true - present", "own - true"}
               for task in per_task.values())
    assert "| windows with t+H inside | present-frame error | joint-sample error | skill |" in (
        out / "report.md").read_text()
    # Clamped windows (whose "true" future is the episode's last frame) read apart from the others.
    by_window = report["oracle_future"]["by_window"]
    assert by_window["t+H inside the episode"]["windows"] == buckets[0]["windows"]
    assert sum(row["windows"] for row in by_window.values()) == overall["own"]["action_error"]["windows"]
    assert by_window["clamped"]["windows"] > 0 and "| clamped |" in (out / "report.md").read_text()


def test_resample_scores_the_policy_with_another_sampler(trained, tmp_path):
    """`resample` changes the sampler of the policy's own samples, as `dust-rl eval resample` does in closed loop;
    the actions of the noise condition, which holds the vision stream still, take the same steps at q = 4 as at 1."""
    policies, _, heldout = trained
    args = ["diagnose", "world-model", "--policy", str(policies["dust"]), "--dataset", str(heldout), "--windows", "32",
            "--batch-size", "16", "--runtime.no-progress", "--runtime.threads", "1"]
    main([*args, "--out", str(tmp_path / "saved")])
    main([*args, "--out", str(tmp_path / "q4"), "resample", "--sampler", "async", "--vision-step-ratio", "4"])
    saved, q4 = (json.loads((tmp_path / name / "report.json").read_text()) for name in ("saved", "q4"))
    assert saved["sampler"]["vision_steps"] == 4 and q4["sampler"]["vision_steps"] == 16
    # 16 Euler steps of the vision stream end elsewhere than 4 (the tiny policy's actions barely read it).
    assert saved["vision_stream"]["joint_sample"]["mean"] != q4["vision_stream"]["joint_sample"]["mean"]
    assert saved["vision_stream"]["buckets"] == q4["vision_stream"]["buckets"]  # one-step estimates: no sampler
    noise = [report["oracle_future"]["conditions"]["noise"]["action_error"] for report in (saved, q4)]
    assert noise[0] == noise[1]
    main([*args, "--out", str(tmp_path / "cold"), "resample", "--noise-scale", "0"])  # every chunk from the mean
    cold = json.loads((tmp_path / "cold" / "report.json").read_text())
    assert cold["sampler"]["noise_scale"] == 0.0
    assert cold["oracle_future"]["conditions"]["own"] != saved["oracle_future"]["conditions"]["own"]
    assert "sampler async (N_A 4, N_o 16)" in (tmp_path / "q4" / "report.md").read_text()
    with pytest.raises(ConfigError, match="does not apply"):
        diagnose(WorldModelDiagnosis(policy=policies["action_only"], dataset=heldout, out=tmp_path / "no",
                                     windows=8, runtime=RuntimeSettings(progress=False),
                                     sampling=SamplerConfig("async", 4, 2)))


def test_an_action_only_policy_has_only_its_own_condition(trained, tmp_path):
    policies, _, heldout = trained
    report = diagnose(WorldModelDiagnosis(policy=policies["action_only"], dataset=heldout, out=tmp_path,
                                          windows=16, runtime=RuntimeSettings(progress=False)))
    assert list(report["oracle_future"]["conditions"]) == ["own"]
    assert "vision_stream" not in report
    assert "| task | windows | own action error |\n" in (tmp_path / "report.md").read_text()


def test_the_training_dataset_is_refused(trained, tmp_path):
    policies, data, _ = trained
    with pytest.raises(DatasetError, match="trained on"):
        diagnose(WorldModelDiagnosis(policy=policies["dust"], dataset=data, out=tmp_path, windows=8,
                                     runtime=RuntimeSettings(progress=False)))


def test_a_dataset_of_other_frames_or_tasks_is_refused(trained, tmp_path):
    policies, _, _ = trained
    other = tmp_path / "other"
    collect_demos(other, tasks=["close_drawer"], episodes=1, env_kwargs={"image_size": 48}, progress=False)
    with pytest.raises(DatasetError, match=r"frames: \[48, 48\] px, the policy was trained on \[32, 32\]; tasks "
                                           r"\['close_drawer'\], which the policy never trained on"):
        diagnose(WorldModelDiagnosis(policy=policies["dust"], dataset=other, out=tmp_path / "d", windows=8,
                                     runtime=RuntimeSettings(progress=False)))
    assert not (tmp_path / "d").exists()


def test_intervals_are_over_episodes_not_windows():
    from dust_rl.diagnose.world_model import mean_interval

    # Two episodes: one of many windows at 1.0, one of a single window at 3.0. Each episode weighs the same.
    values, episode = torch.tensor([1.0] * 9 + [3.0]), torch.tensor([0] * 9 + [1])
    summary = mean_interval(values, episode)
    assert summary["mean"] == 2.0 and summary["episodes"] == 2 and summary["windows"] == 10
    assert summary["ci95_low"] < 1.0 < 3.0 < summary["ci95_high"]  # two episodes tell little
