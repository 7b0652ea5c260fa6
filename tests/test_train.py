"""Imitation training: schedule, EMA, run folder rules, bad input, and resume after kill -9."""

from __future__ import annotations

import dataclasses
import errno
import importlib.util
import io
import json
import math
import os
import pathlib
import re
import shutil
import subprocess

import numpy as np
import pytest
import torch
from conftest import as_before_the_groups, kill_after_first_checkpoint
from crafted import CRAFTS
from PIL import Image
from torchrl.checkpoint import Checkpoint, CheckpointRotation, GlobalRNGState

from dust_rl.agents import PolicyConfig, load_policy, save_image_encoder
from dust_rl.cli import main
from dust_rl.data import DatasetError, DemoDataset, DemoWindows, collect_demos
from dust_rl.data.dataset import cache_root, writable
from dust_rl.data.env_state_norm import INFO_KEY as ENV_STATE_NORM_INFO
from dust_rl.data.env_state_norm import PER_TASK
from dust_rl.data.features import FeatureCache
from dust_rl.data.seeding import VALIDATION_SEED
from dust_rl.data.tools import dataset_summary
from dust_rl.diagnose.world_model import vision_skill, windows_of
from dust_rl.errors import CheckpointError, ConfigError, NoSpaceError
from dust_rl.keys import ACTION_IS_PAD_KEY
from dust_rl.storage.cache_files import CACHE_FOLDERS, cache_files
from dust_rl.storage.checkpoint_dirs import DIGESTS, file_sha256
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint
from dust_rl.storage.lock import FolderLockedError, folder_lock
from dust_rl.storage.run_folder import locked_run_folder, restore
from dust_rl.train.action_free import ActionFreeBatches, with_action_free
from dust_rl.train.dataset_batches import DatasetBatches
from dust_rl.train.imitation import RESUMABLE_FIELDS, SKILL_WINDOWS, TrainConfig, _keep_best, train
from dust_rl.train.optim import averaged_weights, warmup_cosine, weight_average
from dust_rl.train.readout.cache import READOUT_KIND
from dust_rl.train.settings import GROUPS, DataSettings, LoggingSettings, OptimSettings, TrainRuntime

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_POLICY = {"horizon": 4, "execute_steps": 2, "d_model": 32, "n_heads": 2, "n_mmdit": 2, "n_dit": 0}
# Through the command line: every setting at its own default (as TrainConfig in Python), tiny sizes.
TINY_ARGS = ["--recipe=defaults", "--optim.batch-size=8",
             *[f"--model.{k.replace('_', '-')}={v}" for k, v in TINY_POLICY.items()]]
POLICY_FIELDS = {f.name for f in dataclasses.fields(PolicyConfig)}
GROUP_OF = {f.name: group for group, kind in GROUPS.items() for f in dataclasses.fields(kind) if f.name != "lr"}


@pytest.fixture
def run_inputs(demo_dir, tiny_encoder, tmp_path):
    """A private copy of the demo dataset (training caches features inside it) and a tiny encoder file."""
    dataset = shutil.copytree(demo_dir, tmp_path / "data")
    return dataset, save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")


def tiny_policy(encoder, **overrides) -> PolicyConfig:
    return PolicyConfig(**{**TINY_POLICY, "image_encoder": str(encoder), **overrides})


def tiny_config(run_inputs, out, **overrides) -> TrainConfig:
    """A tiny run; overrides naming a :class:`PolicyConfig` field go to the policy, those naming a setting of one
    group (``steps``, ``aux_frames``; not ``lr``, which two groups have) to its group."""
    dataset, encoder = run_inputs
    settings = {"batch_size": 8, "steps": 12, "log_every": 3, "checkpoint_every": 4, "threads": 1,
                "progress": False} | {k: v for k, v in overrides.items() if k not in POLICY_FIELDS}
    groups = {group: kind(**{k: v for k, v in settings.items() if GROUP_OF.get(k) == group})
              for group, kind in GROUPS.items()}
    policy = tiny_policy(encoder, **{k: v for k, v in overrides.items() if k in POLICY_FIELDS})
    return TrainConfig(dataset=dataset, out=out, policy=policy, **groups,
                       **{k: v for k, v in settings.items() if k not in GROUP_OF})


def trained_weights(path) -> dict[str, torch.Tensor]:
    return {k: v for k, v in load_policy(path).state_dict().items() if not k.startswith("backbone.")}


def test_warmup_cosine_schedule():
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=2.0)
    schedule = warmup_cosine(optimizer, 100, 0.1)
    factors = []
    for _ in range(100):
        factors.append(schedule.get_last_lr()[0] / 2.0)
        optimizer.step()
        schedule.step()
    expected = [(s + 1) / 10 for s in range(10)]
    expected += [0.5 * (1 + math.cos(math.pi * (s - 10) / 90)) for s in range(10, 100)]
    torch.testing.assert_close(torch.tensor(factors, dtype=torch.float64), torch.tensor(expected, dtype=torch.float64))
    assert factors[99] < 0.01


def test_ema_ramps_up_and_round_trips():
    module = torch.nn.Linear(3, 2)
    ema = weight_average(module, decay=0.9)
    start = module.weight.detach().clone()
    with torch.no_grad():
        module.weight.add_(1.0)
    ema.update_parameters(module)  # the second average: decay min(0.9, 2/11)
    expected = start + (1 - 2 / 11)
    with averaged_weights(ema, module):
        torch.testing.assert_close(module.weight.detach(), expected)
    torch.testing.assert_close(module.weight.detach(), start + 1)  # own weights back outside
    copy = weight_average(torch.nn.Linear(3, 2), decay=0.9)
    copy.load_state_dict(ema.state_dict())
    assert copy.n_averaged.item() == 2 and torch.equal(copy.module.weight, ema.module.weight)
    with pytest.raises(ValueError, match="EMA decay must be in"):
        weight_average(module, decay=1.0)


def test_tiny_run_writes_policy_logs_and_config(run_inputs, tmp_path):
    out = tmp_path / "run"
    config = tiny_config(run_inputs, out, eval_every=12, eval_episodes=1, eval_workers=1)
    # a learning rate at which 12 steps move every trained weight visibly (the skill check below)
    config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=1e-2, warmup=0.0))
    result = train(config, command="dust-rl train ...")
    policy = load_policy(result.policy)
    assert policy.config.horizon == 4 and policy.execute_steps == 2
    assert policy.info["env_id"] == "DustFranka-v0" and policy.info["tasks"] == ["press_button", "open_drawer"]
    assert policy.info["image_size"] == [32, 32]  # the frames it was trained on, checked against an env on load
    stored = json.loads((out / "config.json").read_text())
    assert stored["command"] == "dust-rl train ..." and stored["config"]["optim"]["steps"] == 12
    rows = (out / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text().split()
    assert [int(r.split(",")[0]) for r in rows] == [3, 6, 9, 12]
    assert list((out / "logs" / "train").glob("events.out.tfevents.*"))
    timing = json.loads((out / "timing.json").read_text())  # where the run's time went
    assert timing["steps"] == 12 and "cores" in timing["machine"]
    phases = timing["phases"]
    assert {phases[f"step: {part}"]["count"] for part in ("data", "forward", "backward", "optimizer")} == {12}
    assert phases["checkpoint"]["count"] == 3 and phases["periodic eval"]["count"] == 1
    assert all(row["seconds"] > 0 for row in phases.values())
    # The periodic closed-loop evaluation ran on every training task and logged its success rates.
    evaluated = json.loads((out / "eval" / "step-0000012" / "report.json").read_text())
    assert [row["task"] for row in evaluated["tasks"]] == ["press_button", "open_drawer"]
    assert evaluated["seeds"][0] == VALIDATION_SEED  # chosen on validation seeds, the held-out ones left unseen
    success = (out / "logs" / "train" / "scalars" / "eval" / "success_rate.csv").read_text().split(",")
    assert int(success[0]) == 12 and float(success[1]) == evaluated["overall"]["success_rate"]
    step, skill = (out / "logs" / "train" / "scalars" / "wm" / "skill.csv").read_text().split(",")
    assert int(step) == 12 and math.isfinite(float(skill)) and float(skill) < 1  # a world model's skill, logged
    # ... of the weights evaluated then, the condition layers included (whose tokens change as they train): the
    # skill of the evaluated policy file on the same windows, computed anew.
    evaluated_policy = load_policy(out / "eval" / "step-0000012" / "policy.pt")
    windows = windows_of(evaluated_policy, FeatureCache(DemoDataset(tmp_path / "data"), evaluated_policy,
                                                        progress=False, store=True), SKILL_WINDOWS, seed=0)
    again = vision_skill(evaluated_policy, windows, buckets=1, seed=0, batch_size=8)["joint_sample"]["skill"]
    assert float(skill) == pytest.approx(again, rel=64 * torch.finfo(torch.float32).eps)
    assert [p.name for p in sorted((out / "checkpoints").iterdir())] == ["checkpoint-000000000008",
                                                                        "checkpoint-000000000012"]
    assert (out / "loss.png").stat().st_size > 0
    assert list((tmp_path / "data" / "features").glob("*.npy"))  # cached for the next run on this dataset


def test_tensorboard_gets_the_config_the_success_plot_and_a_rollout_video_under_the_runs_name(run_inputs, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData
    from tensorboard.util.tensor_util import make_ndarray

    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=2, log_every=1, eval_every=2, eval_episodes=1, eval_workers=1,
                      run_name="trial"))
    logs = out / "logs"
    assert (logs / "trial" / "scalars" / "train" / "loss.csv").is_file() and not (logs / "train").exists()
    events = EventAccumulator(str(logs / "trial"), size_guidance={"images": 0, "tensors": 0})
    events.Reload()
    (plot,) = events.Images("eval/success")
    assert plot.step == 2 and plot.encoded_image_string.startswith(b"\x89PNG")
    # The video: the periodic evaluation's first episode, every observation a frame of an animated GIF.
    (video,) = events.Images("eval/rollout/press_button")
    evaluated = json.loads((out / "eval" / "step-0000002" / "report.json").read_text())
    episode = evaluated["tasks"][0]["videos"][0]
    with Image.open(io.BytesIO(video.encoded_image_string)) as gif:
        assert (video.step, gif.format, gif.n_frames, gif.size) == (2, "GIF", episode["length"] + 1,
                                                                      (video.width, video.height))
    # The config, as text (its JSON) and as hparams by dotted name.
    (text,) = events.Tensors("config/text_summary")
    stored = json.loads((out / "config.json").read_text())["config"]
    assert json.loads(make_ndarray(text.tensor_proto).item().decode()) == stored
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = HParamsPluginData.FromString(content).session_start_info.hparams
    assert (hparams["optim.steps"].number_value, hparams["logging.run_name"].string_value) == (2, "trial")
    experiment = HParamsPluginData.FromString(events.PluginTagToContent("hparams")["_hparams_/experiment"]).experiment
    assert [m.name.tag for m in experiment.metric_infos] == ["train/loss", "eval/success_rate"]
    with pytest.raises(ConfigError, match=r"--logging.run-name must name one folder .*, got '../x'"):
        tiny_config(run_inputs, out, run_name="../x")


def test_loggers_are_chosen_by_name(run_inputs, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=2, log_every=1, loggers=("csv",)))
    assert (out / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text().count("\n") == 2
    assert not list((out / "logs").rglob("events.out.tfevents.*"))
    with pytest.raises(ConfigError, match=r"unknown loggers \['visdom'\]"):
        tiny_config(run_inputs, out, loggers=("csv", "visdom"))
    if importlib.util.find_spec("wandb") is None:  # refused before any work, as dust-rl finetune does
        with pytest.raises(ConfigError, match=r"--loggers wandb needs the wandb package: pip install wandb"):
            tiny_config(run_inputs, out, loggers=("csv", "wandb"))


@pytest.mark.parametrize("source", ["features", "pixels"])
def test_keypoints_learn_from_the_privileged_state(source, run_inputs, tmp_path):
    out = tmp_path / "run"
    result = train(tiny_config(run_inputs, out, steps=3, log_every=3, keypoints=2, keypoint_source=source,
                               lambda_aux=0.5))
    config = load_policy(result.policy).config
    width = len(json.loads((run_inputs[0] / "meta.json").read_text())["stats"]["observation.environment_state"]["mean"])
    assert (config.keypoints, config.keypoint_source, config.aux_state_dim, config.lambda_aux) == (
        2, source, width, 0.5) and width > 0
    aux = (out / "logs" / "train" / "scalars" / "train" / "loss_aux.csv").read_text().split(",")
    assert int(aux[0]) == 3 and math.isfinite(float(aux[1])) and float(aux[1]) > 0


@pytest.mark.parametrize("readout", [{"keypoints": 2, "keypoint_source": "pixels"}, {"readout": "tokens"}])
def test_training_logs_the_aux_frame_loss(readout, run_inputs, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=2, log_every=2, lambda_aux=1.0, aux_frames=3, **readout))
    step, value = (out / "logs" / "train" / "scalars" / "train" / "loss_aux_frames.csv").read_text().split(",")
    assert int(step) == 2 and float(value) > 0
    with pytest.raises(ConfigError, match="aux-frames needs --model.lambda-aux > 0 and a read-out frames can"):
        tiny_config(run_inputs, out, keypoints=2, lambda_aux=1.0, aux_frames=3)


def test_readout_warmup_freezes_the_readout_and_resumes(run_inputs, tmp_path):
    def run(out, steps, **extra):
        return train(tiny_config(run_inputs, out, steps=steps, checkpoint_every=2, keypoints=2,
                                 keypoint_source="pixels", lambda_aux=1.0, aux_frames=3, warmup_steps=3, **extra))

    short, long = trained_weights(run(tmp_path / "short", 2).policy), trained_weights(run(tmp_path / "long", 4).policy)
    readout = [k for k in short if k.startswith(("condition.keypoints.", "state_readout."))]
    assert readout and all(torch.equal(short[k], long[k]) for k in readout)  # warmed, then never moved
    assert any(not torch.equal(short[k], long[k]) for k in short if k.startswith("model."))
    warm = (tmp_path / "long" / "logs" / "train" / "scalars" / "warmup" / "loss_aux_frames.csv").read_text().split(",")
    assert int(warm[0]) == 3 and float(warm[1]) > 0
    heldout = tmp_path / "long" / "logs" / "train" / "scalars" / "warmup" / "loss_aux_frames_heldout.csv"
    step, value = heldout.read_text().split(",")  # frames never fitted: how well the positions generalise
    assert int(step) == 3 and math.isfinite(float(value)) and float(value) > 0
    # Resuming from step 2 skips the warm-up (the checkpoint holds it) and ends where the straight run did.
    shutil.rmtree(sorted((tmp_path / "long" / "checkpoints").iterdir())[-1])
    (tmp_path / "long" / "policy.pt").unlink()
    resumed = trained_weights(run(tmp_path / "long", 4, resume=True).policy)
    assert [k for k in long if not torch.equal(resumed[k], long[k])] == []
    with pytest.raises(ConfigError, match="warmup-steps needs --readout.aux-frames"):
        tiny_config(run_inputs, tmp_path / "x", keypoints=2, keypoint_source="pixels", lambda_aux=1.0,
                    warmup_steps=3)


def test_a_warmed_readout_is_cached_shared_by_the_variants_and_changes_nothing_else(run_inputs, tmp_path):
    readout = {"readout": "tokens", "lambda_aux": 1.0, "aux_state_input": True, "aux_frames": 3, "warmup_steps": 3,
               "demos": False, "steps": 2}
    cache = run_inputs[0] / "readout_cache"
    dust = trained_weights(train(tiny_config(run_inputs, tmp_path / "dust", **readout)).policy)
    assert len(list(cache.glob("*.pt"))) == 1
    action_only = trained_weights(train(tiny_config(run_inputs, tmp_path / "ao", variant="action_only",
                                                    **readout)).policy)
    assert len(list(cache.glob("*.pt"))) == 1  # the second variant loaded the first one's fit
    fitted = [k for k in dust if k.startswith("state_readout.")]
    assert fitted and all(torch.equal(dust[k], action_only[k]) for k in fitted)
    logs = [tmp_path / run / "logs" / "train" / "scalars" / "warmup" / "loss_aux_frames_heldout.csv"
            for run in ("dust", "ao")]
    assert logs[0].read_text() == logs[1].read_text() != ""  # the cached fit's scalars are replayed

    # Training after a cached warm-up is the run that fitted it, bit for bit; a damaged cache file is refused, one
    # without its record (an older version's) is refitted.
    again = trained_weights(train(tiny_config(run_inputs, tmp_path / "again", **readout)).policy)
    assert all(torch.equal(dust[k], again[k]) for k in dust)
    fit = next(cache.glob("*.pt"))
    fit.write_bytes(b"not a checkpoint")
    with pytest.raises(DatasetError, match="this cache changed since it was written"):
        train(tiny_config(run_inputs, tmp_path / "damaged", **readout))
    fit.with_name(fit.name + ".sha256").unlink()
    refitted = trained_weights(train(tiny_config(run_inputs, tmp_path / "refit", **readout)).policy)
    assert all(torch.equal(dust[k], refitted[k]) for k in dust)
    # Another warm-up setting is another fit.
    other = tiny_config(run_inputs, tmp_path / "lr", **readout)
    train(dataclasses.replace(other, readout=dataclasses.replace(other.readout, lr=3e-3)))
    assert len(list(cache.glob("*.pt"))) == 2


def test_resume_after_kill_matches_an_uninterrupted_run(run_inputs, tmp_path):
    steps = 600
    reference = train(tiny_config(run_inputs, tmp_path / "ref", steps=steps, checkpoint_every=50))
    out = tmp_path / "killed"
    dataset, encoder = run_inputs
    args = ["train", "--dataset", str(dataset), "--out", str(out), "--model.image-encoder", str(encoder),
            "--optim.steps", str(steps), "--logging.checkpoint-every", "50", "--logging.log-every", "3",
            "--runtime.threads", "1", "--runtime.no-progress",
            *TINY_ARGS]
    kill_after_first_checkpoint(args, out)
    assert not (out / "policy.pt").exists()

    with pytest.raises(FileExistsError, match="--resume"):
        train(tiny_config(run_inputs, out, steps=steps, checkpoint_every=50))
    resumed = train(tiny_config(run_inputs, out, steps=steps, checkpoint_every=50, resume=True))
    ref, got = trained_weights(reference.policy), trained_weights(resumed.policy)
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


def _as_written_on_a_gpu(checkpoint) -> None:
    """Rewrite a CPU checkpoint into the files a CUDA run writes: every tensor recorded on ``cuda:0`` (in the
    schemas and the memmap metadata) and a CUDA generator state beside the CPU one."""
    for meta in [*checkpoint.rglob("state.json"), *checkpoint.rglob("meta.json")]:
        meta.write_text(re.sub(r'"device":\s*"cpu"', '"device": "cuda:0"', meta.read_text()))
    rng = next(checkpoint.glob("components/*-rng")) / "state.json"
    schema = json.loads(rng.read_text())
    cpu_state = dict((key["value"], value) for key, value in schema["items"])["torch_cpu"]
    schema["items"].append([{"kind": "value", "value": "torch_cuda"}, {"kind": "list", "items": [cpu_state]}])
    rng.write_text(json.dumps(schema))
    _record_digests(checkpoint)


@pytest.mark.skipif(torch.cuda.is_available(), reason="resumes a GPU run where CUDA is absent")
def test_a_run_checkpointed_on_a_gpu_resumes_on_a_cpu(run_inputs, tmp_path):
    reference = train(tiny_config(run_inputs, tmp_path / "ref", steps=8, checkpoint_every=4))
    out = tmp_path / "gpu"
    train(tiny_config(run_inputs, out, steps=8, checkpoint_every=4))
    checkpoints = sorted((out / "checkpoints").glob("checkpoint-*"))
    shutil.rmtree(checkpoints[-1])  # back to step 4, as a run stopped there leaves it
    (out / "policy.pt").unlink()
    _as_written_on_a_gpu(checkpoints[0])
    with pytest.raises(CheckpointError, match="CUDA is unavailable"):  # torchrl's own RNG state refuses it
        restore(Checkpoint(rng=GlobalRNGState()), CheckpointRotation(out / "checkpoints", keep_last=2))
    with pytest.warns(UserWarning, match="without the saved torch_cuda random state"):
        resumed = train(tiny_config(run_inputs, out, steps=8, checkpoint_every=4, resume=True))
    ref, got = trained_weights(reference.policy), trained_weights(resumed.policy)
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


def test_resume_refuses_other_settings_and_broken_checkpoints(run_inputs, tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing to resume"):
        train(tiny_config(run_inputs, tmp_path / "none", resume=True))
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=4))
    config = tiny_config(run_inputs, out, steps=4, resume=True)
    with pytest.raises(ConfigError, match=r"other settings \(optim\.lr\)"):
        train(dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=1e-3)))
    # A run started before a field existed stored none: it resumes at the field's default, not at another value.
    saved = json.loads((out / "config.json").read_text())
    del saved["config"]["readout"]["lr"]
    (out / "config.json").write_text(json.dumps(saved))
    train(config)
    other_readout_lr = dataclasses.replace(config, readout=dataclasses.replace(config.readout, lr=3e-3))
    with pytest.raises(ConfigError, match=r"other settings \(readout\.lr\)"):
        train(other_readout_lr)
    # A run started before the settings were grouped stored them at the top level: they are read as their groups'.
    saved["config"] = as_before_the_groups(saved["config"])
    (out / "config.json").write_text(json.dumps(saved))
    assert saved["config"]["steps"] == 4 and "optim" not in saved["config"]
    train(config)
    (out / "config.json").write_text(json.dumps({**saved, "config": {**saved["config"], "lr": 1e-3}}))
    with pytest.raises(ConfigError, match=r"other settings \(optim\.lr\)"):
        train(config)
    (out / "config.json").write_text(json.dumps(saved))
    latest = sorted((out / "checkpoints").iterdir())[-1]
    for state in latest.rglob("*.memmap"):
        state.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="cannot resume"):
        train(tiny_config(run_inputs, out, steps=4, resume=True))


def test_the_world_model_target_can_be_another_camera(run_inputs, tmp_path):
    result = train(tiny_config(run_inputs, tmp_path / "wrist", steps=4, future_camera="wrist"))
    policy = load_policy(result.policy)
    assert policy.future_camera == "wrist" and policy.cameras == ["front", "wrist"]
    tokens = torch.stack([torch.zeros(policy.config.n_image_tokens, policy.config.vision_dim),
                          torch.ones(policy.config.n_image_tokens, policy.config.vision_dim)])
    assert torch.equal(policy.future_targets(tokens), torch.ones(policy.config.n_vision_tokens,
                                                                 policy.config.vision_dim))  # the wrist's
    with pytest.raises(ConfigError, match="future_camera 'top' is not among the cameras"):
        train(tiny_config(run_inputs, tmp_path / "top", steps=4, future_camera="top"))


@pytest.mark.parametrize("vision_grid", [(1, 1), (2, 2)])
def test_the_world_model_target_is_standardised_after_pooling(run_inputs, tmp_path, vision_grid):
    """Each target channel has zero mean and unit variance over the dataset's frames at any grid, so lambda_wm
    weighs a coarse target as much as a fine one."""
    policy = load_policy(train(tiny_config(run_inputs, tmp_path / "run", steps=1, vision_grid=vision_grid)).policy)
    dataset = DemoDataset(run_inputs[0])
    windows = DemoWindows(dataset, horizon=policy.config.horizon, images=False)
    frames = policy.present_target(FeatureCache(dataset, policy, progress=False).batch(
        next(windows.iterate(len(dataset))))).double().flatten(0, 1)  # every row's frame, each token
    assert frames.shape == (len(dataset) * math.prod(vision_grid), policy.config.vision_dim)
    tolerance = 10 * torch.finfo(torch.float32).eps * frames.abs().max().item()
    torch.testing.assert_close(frames.mean(0), torch.zeros(frames.shape[-1], dtype=torch.float64),
                               rtol=0, atol=tolerance)
    torch.testing.assert_close(frames.std(0), torch.ones(frames.shape[-1], dtype=torch.float64),
                               rtol=0, atol=tolerance)
    assert not torch.equal(policy.normalizer.future_std, torch.ones_like(policy.normalizer.future_std))


def test_the_world_model_target_can_be_nearer_than_the_chunks_end(run_inputs, tmp_path):
    policy = load_policy(train(tiny_config(run_inputs, tmp_path / "near", steps=1, future_offset=1)).policy)
    assert policy.config.future_steps == 1 and PolicyConfig(horizon=5).future_steps == 5  # default: the chunk's end
    dataset = DemoDataset(run_inputs[0])
    windows = DatasetBatches(dataset, policy, 4, progress=False).windows
    every = next(windows.iterate(len(dataset)))
    last = dataset.row_episode_end[every["index"]] - 1
    assert torch.equal(every["future", "index"], torch.minimum(every["index"] + 1, last))
    with pytest.raises(ValueError, match=r"future_offset must be an int in \[1, "):
        tiny_config(run_inputs, tmp_path / "bad", future_offset=0)


def test_a_change_target_is_the_motion_in_units_of_its_rms(run_inputs, tmp_path):
    policy = load_policy(train(tiny_config(run_inputs, tmp_path / "change", steps=4,
                                           future_target="change")).policy)
    dataset = DemoDataset(run_inputs[0])
    features = FeatureCache(dataset, policy, progress=False)
    windows = DemoWindows(dataset, horizon=policy.config.horizon, images=False)
    batch = features.batch(next(windows.iterate(len(dataset))))  # every window
    moving = ~batch.get("future_is_clamped")
    target = policy._model_batch(batch).get("future_tokens")
    assert policy.normalizer.future_change_scale != 1.0
    # The scale is the changes' RMS over the dataset, so the targets of unclamped windows have unit RMS.
    assert math.isclose(target[moving].double().square().mean().sqrt().item(), 1.0,
                        rel_tol=100 * torch.finfo(torch.float32).eps)
    # Acting adds the present frame back: the target, decoded, is the real future frame.
    frame = policy.standardised_future(batch.get("future_tokens"))
    torch.testing.assert_close(policy._predicted_frame(target, batch), frame)
    with pytest.raises(ValueError, match="unknown future_target 'delta'"):
        tiny_config(run_inputs, tmp_path / "bad", future_target="delta")


def test_bad_training_input_is_named(run_inputs, tmp_path):
    with pytest.raises(ValueError, match=r"execute_steps must be in \[1, horizon=4\], got 9"):
        tiny_config(run_inputs, tmp_path / "a", execute_steps=9)
    with pytest.raises(ValueError, match="lambda_aux with readout 'keypoints' needs keypoints"):
        tiny_config(run_inputs, tmp_path / "a", lambda_aux=1.0)
    dataset, _ = run_inputs
    meta = json.loads((dataset / "meta.json").read_text())
    meta["env_kwargs"]["image_size"] = 48  # the env would render other images than the dataset holds
    (dataset / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="does not match the requested env"):
        train(tiny_config(run_inputs, tmp_path / "b"))


def test_action_free_episodes_train_the_world_model_but_not_the_actions(run_inputs, demo_dir, tmp_path):
    video_dir = shutil.copytree(demo_dir, tmp_path / "video")
    result = train(tiny_config(run_inputs, tmp_path / "run", steps=2, video_dataset=video_dir, video_fraction=0.5))
    policy = load_policy(result.policy)
    assert policy.info["video_dataset"] == str(video_dir) and any((video_dir / "features").iterdir())
    # Their rows carry no action label: NaN actions there change no loss, while the vision loss counts them.
    dataset, _ = run_inputs
    features = FeatureCache(DemoDataset(dataset), policy, progress=False)
    windows = DemoWindows(DemoDataset(dataset), horizon=policy.config.horizon, batch_size=4, images=False)
    action_free = ActionFreeBatches(DemoDataset(video_dir), policy, 4, progress=False).sample()
    assert not action_free.get("has_action").any() and action_free.get(ACTION_IS_PAD_KEY).all()
    batch = with_action_free(features.batch(windows.sample()), action_free)
    poisoned = batch.clone()
    poisoned.get("action_chunk")[4:] = float("nan")
    losses, poisoned_losses = (policy.compute_loss(b, torch.Generator().manual_seed(0)) for b in (batch, poisoned))
    assert torch.equal(losses["loss_action"], poisoned_losses["loss_action"]) and torch.isfinite(losses["loss"])
    with pytest.raises(ConfigError, match="video_fraction must be in"):
        tiny_config(run_inputs, tmp_path / "x", video_dataset=video_dir, video_fraction=1.0)


def test_action_free_episodes_beside_a_read_out_need_it_frozen_and_the_same_tasks(run_inputs, demo_dir, tmp_path):
    video_dir = shutil.copytree(demo_dir, tmp_path / "video")
    readout = {"readout": "tokens", "lambda_aux": 1.0, "aux_frames": 2, "video_dataset": video_dir}
    with pytest.raises(ConfigError, match="needs --readout.warmup-steps"):
        tiny_config(run_inputs, tmp_path / "x", **readout)
    result = train(tiny_config(run_inputs, tmp_path / "run", steps=2, warmup_steps=2, **readout))
    assert load_policy(result.policy).info["video_dataset"] == str(video_dir)
    meta = json.loads((video_dir / "meta.json").read_text())
    (video_dir / "meta.json").write_text(json.dumps({**meta, "tasks": [*meta["tasks"], "stack"]}))
    with pytest.raises(DatasetError, match="object state means something else"):
        train(tiny_config(run_inputs, tmp_path / "other", steps=2, warmup_steps=2, **readout))


def test_fine_tuning_starts_from_a_policy_and_mixes_in_a_second_dataset(run_inputs, demo_dir, tmp_path):
    readout = {"readout": "tokens", "lambda_aux": 1.0, "aux_frames": 2, "warmup_steps": 2}
    base = train(tiny_config(run_inputs, tmp_path / "base", steps=2, **readout)).policy
    extra_dir = shutil.copytree(demo_dir, tmp_path / "rollouts")
    dataset, encoder = run_inputs
    quiet = TrainRuntime(threads=1, progress=False)
    config = TrainConfig(dataset=dataset, out=tmp_path / "tuned", init_policy=base, runtime=quiet,
                         data=DataSettings(extra_dataset=extra_dir), optim=OptimSettings(batch_size=8, steps=3))
    tuned = load_policy(train(config).policy)
    assert tuned.info["init_policy"] == str(base) and tuned.info["extra_dataset"] == str(extra_dir)
    # The frozen read-out keeps the object-state units it was trained in: an older policy's stay the pooled ones.
    assert tuned.info[ENV_STATE_NORM_INFO] == load_policy(base).info[ENV_STATE_NORM_INFO] == PER_TASK
    older = tmp_path / "older.pt"
    payload = torch.load(base, weights_only=True)
    payload["info"].pop(ENV_STATE_NORM_INFO)
    torch.save(payload, older)
    again = TrainConfig(dataset=dataset, out=tmp_path / "tuned_older", init_policy=older, runtime=quiet,
                        optim=OptimSettings(batch_size=8, steps=1))
    assert load_policy(train(again).policy).info.get(ENV_STATE_NORM_INFO) is None
    assert any((extra_dir / "features").iterdir())  # its frames were encoded and cached
    before, after = trained_weights(base), trained_weights(tmp_path / "tuned" / "policy.pt")
    assert [k for k in before if k.startswith("normalizer.") and not torch.equal(before[k], after[k])] == []
    assert all(torch.equal(before[k], after[k]) for k in before if k.startswith("state_readout."))  # kept frozen
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("model."))
    # Extra rows train with their actions, unlike action-free video: a NaN action there reaches the loss.
    extra = DatasetBatches(DemoDataset(extra_dir), tuned, 4, action_key="action", progress=False).sample()
    extra.get("action_chunk")[0] = float("nan")
    assert torch.isnan(tuned.compute_loss(extra, torch.Generator().manual_seed(0))["loss_action"])
    with pytest.raises(ConfigError, match="--model.\\* flags do not apply with init_policy"):
        tiny_config(run_inputs, tmp_path / "x", init_policy=base)
    with pytest.raises(ConfigError, match="extra_fraction must be in"):
        DataSettings(extra_dataset=extra_dir, extra_fraction=0.0)
    with pytest.raises(ConfigError, match=r"video_fraction \+ extra_fraction must be below 1"):
        DataSettings(extra_dataset=extra_dir, video_dataset=extra_dir, video_fraction=0.5)
    elsewhere = dataclasses.replace(config, out=tmp_path / "other", init_policy=tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="missing.pt"):
        train(elsewhere)
    larger = tmp_path / "rollouts48"  # frames of another size would be mixed into every batch
    collect_demos(larger, tasks=["press_button"], episodes=1, env_kwargs={"image_size": 48}, progress=False)
    with pytest.raises(DatasetError, match=f"{larger} does not match the requested env"):
        train(dataclasses.replace(config, out=tmp_path / "mixed", data=DataSettings(extra_dataset=larger)))
    assert not (tmp_path / "mixed").exists()


def _newest_state(out, component: str = "model"):
    """The memmap folder of ``component`` in the run's newest checkpoint."""
    latest = sorted((out / "checkpoints").glob("checkpoint-*"))[-1]
    return next((latest / "components").glob(f"*-{component}")) / "state"


def _record_digests(checkpoint) -> None:
    """Rewrite ``digests.json`` to match the folder, as a crafter would: the checks must hold without it."""
    files = [p for p in checkpoint.rglob("*") if p.is_file() and p.name != DIGESTS]
    (checkpoint / DIGESTS).write_text(json.dumps({"files": {p.relative_to(checkpoint).as_posix(): {
        "size": p.stat().st_size, "sha256": file_sha256(p)} for p in files}}))


def _component_outside(state, marker):
    """The manifest points the model component at a folder outside the checkpoint, one holding a pickle."""
    outside = shutil.copytree(state.parent, state.parents[4] / "elsewhere")
    CRAFTS["entry"](outside / "state", marker)
    manifest = state.parents[2] / "manifest.json"
    saved = json.loads(manifest.read_text())
    saved["components"]["model"]["path"] = os.path.relpath(outside, manifest.parent)
    manifest.write_text(json.dumps(saved))


def _component_linked_out(state, marker):
    """The model component's folder is a symlink to one outside the checkpoint, holding a pickle."""
    outside = shutil.copytree(state.parent, state.parents[4] / "elsewhere")
    CRAFTS["entry"](outside / "state", marker)
    shutil.rmtree(state.parent)
    os.symlink(outside, state.parent)


def _weights_only_payload(state, marker):
    """A ``state.pt`` beside the memmap folder: torchrl's adapter would read it first."""
    torch.save({"x": torch.zeros(1)}, state.parent / "state.pt")


CHECKPOINT_CRAFTS = {**CRAFTS, "component-outside": _component_outside, "component-linked-out": _component_linked_out,
                     "state-pt": _weights_only_payload}


@pytest.mark.parametrize("craft", CHECKPOINT_CRAFTS)
def test_a_pickle_grafted_into_a_checkpoint_never_runs_on_resume(craft, run_inputs, tmp_path):
    out, marker = tmp_path / "run", tmp_path / "code-ran"
    train(tiny_config(run_inputs, out, steps=4))
    policy = (out / "policy.pt").read_bytes()
    state = _newest_state(out)
    CHECKPOINT_CRAFTS[craft](state, marker)
    _record_digests(state.parents[2])
    with pytest.raises(CheckpointError, match=r"cannot resume from this checkpoint .*refused") as error:
        train(tiny_config(run_inputs, out, steps=4, resume=True))
    assert "\n" not in str(error.value)
    assert not marker.exists()
    assert (out / "policy.pt").read_bytes() == policy


@pytest.mark.parametrize("damage,problem", [("truncated", "truncated"), ("flipped", "SHA-256 differs"),
                                            ("no-digests", "digests.json: missing")])
def test_a_damaged_checkpoint_is_refused_and_nothing_is_overwritten(damage, problem, run_inputs, tmp_path):
    out = tmp_path / "run"
    dataset, encoder = run_inputs
    args = ["train", "--dataset", str(dataset), "--out", str(out), "--model.image-encoder", str(encoder),
            "--optim.steps", "4", "--logging.checkpoint-every", "4", "--logging.log-every", "3",
            "--runtime.threads", "1", "--runtime.no-progress",
            *TINY_ARGS]
    main(args)
    policy = (out / "policy.pt").read_bytes()
    state = _newest_state(out)
    tensor = max(state.glob("*.memmap"), key=lambda p: p.stat().st_size)
    if damage == "truncated":  # as a full disk or a killed copy leaves it: it used to load as zeros
        os.truncate(tensor, tensor.stat().st_size // 2)
    elif damage == "flipped":
        data = bytearray(tensor.read_bytes())
        data[len(data) // 2] ^= 0xFF
        tensor.write_bytes(bytes(data))
    else:
        (state.parents[2] / DIGESTS).unlink()
    with pytest.raises(SystemExit, match=rf"^dust-rl: error: .*cannot resume from this checkpoint .*{problem}") \
            as error:
        main([*args, "--resume"])
    assert "\n" not in str(error.value)
    assert (out / "policy.pt").read_bytes() == policy


def test_resume_refuses_a_dataset_that_changed_since_the_checkpoint(run_inputs, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=4))
    policy = (out / "policy.pt").read_bytes()
    dataset, _ = run_inputs
    collect_demos(dataset, tasks=["press_button"], episodes=4, env_kwargs={"image_size": 32}, progress=False)
    with pytest.raises(DatasetError, match=r"changed since this run.s checkpoint \(data, num_rows, episodes_per"):
        train(tiny_config(run_inputs, out, steps=4, resume=True))
    assert (out / "policy.pt").read_bytes() == policy


def test_a_second_run_into_a_busy_folder_is_refused_naming_the_first(run_inputs, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    with folder_lock(out), pytest.raises(FolderLockedError, match=f"pid {os.getpid()}"):  # as a run holds it
        train(tiny_config(run_inputs, out, steps=2))
    assert sorted(p.name for p in out.iterdir()) == [".lock"]  # nothing of the refused run's
    # A run holds the lock until its end, then lets go (its details gone with it): --resume runs.
    train(tiny_config(run_inputs, out, steps=2))
    assert (out / ".lock").read_bytes() == b""
    train(tiny_config(run_inputs, out, steps=2, resume=True))
    # Refused under the lock (the folder changed since the first check), a run leaves no folder it created.
    fresh = tmp_path / "fresh" / "run"
    with (pytest.raises(FileNotFoundError, match="nothing to resume"),
          locked_run_folder(tiny_config(run_inputs, fresh, resume=True), RESUMABLE_FIELDS, None)):
        pass
    assert not fresh.exists()
    with pytest.raises(DatasetError):
        train(tiny_config((tmp_path / "missing", run_inputs[1]), tmp_path / "other"))
    assert not (tmp_path / "other").exists()


@pytest.fixture
def read_only():
    """Make a folder read-only for this process, as a user's dataset on a read-only share is: by its mode, or
    (root ignores modes) by the immutable attribute; skips where neither holds."""
    made = []

    def make(folder):
        folder.chmod(0o555)
        made.append(folder)
        if writable(folder) and shutil.which("chattr"):
            subprocess.run(["chattr", "+i", str(folder)], check=False, capture_output=True)
        if writable(folder):
            pytest.skip("cannot make a folder read-only for this process here")
        return folder

    yield make
    for folder in made:
        if shutil.which("chattr"):
            subprocess.run(["chattr", "-i", str(folder)], check=False, capture_output=True)
        folder.chmod(0o755)


def test_a_read_only_dataset_keeps_its_caches_in_a_cache_folder(run_inputs, tmp_path, monkeypatch, read_only):
    dataset, _ = run_inputs
    identity = DemoDataset(dataset).identity
    assert cache_root(dataset, identity) == dataset  # writable: the caches stay with the data
    named = cache_root(dataset, identity, tmp_path / "mine")
    assert named.parent == tmp_path / "mine" and named != cache_root(dataset, {**identity, "num_rows": 1},
                                                                        tmp_path / "mine")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    before = sorted(p.name for p in dataset.iterdir())
    read_only(dataset)
    fallback = cache_root(dataset, identity)
    assert fallback.parent == tmp_path / "xdg" / "dust-rl"
    config = tiny_config(run_inputs, tmp_path / "run", steps=2, aux_frames=8, lambda_aux=1.0, readout="tokens",
                         warmup_steps=2, demos=False)
    train(config)
    assert list((fallback / "features").glob("*.npy")) and list((fallback / "aux_frames").iterdir())
    assert list((fallback / "readout_cache").iterdir())
    assert sorted(p.name for p in dataset.iterdir()) == before
    train(dataclasses.replace(config, out=tmp_path / "run2", cache_dir=tmp_path / "mine"))  # --cache-dir
    assert list((cache_root(dataset, identity, tmp_path / "mine") / "features").glob("*.npy"))


def test_a_cache_changed_since_it_was_written_is_refused_and_dataset_info_lists_them(run_inputs, tmp_path):
    dataset, _ = run_inputs
    for folder in CACHE_FOLDERS:  # caches other tests left in the shared dataset are not this run's
        shutil.rmtree(dataset / folder, ignore_errors=True)
    config = tiny_config(run_inputs, tmp_path / "run", steps=2, aux_frames=8, lambda_aux=1.0, readout="tokens",
                         warmup_steps=2, demos=False)
    train(config)
    caches = {path.name: path for path, _ in cache_files(dataset)}
    listed = dataset_summary(DemoDataset(dataset))
    assert len(caches) == 6 and all(f"{p.relative_to(dataset)} (" in listed for p in caches.values()), listed
    [features] = [p for p in caches.values() if p.parent.name == "features"]
    [readout] = [p for p in caches.values() if p.parent.name == "readout_cache"]
    frames = next(p for p in caches.values() if p.suffix == ".npz")  # fitted on and held out: 2 of each
    tokens = next(p for p in caches.values() if ".tokens-" in p.name)
    runs = iter(range(10))

    def refused_when(path, poison):
        original = path.read_bytes()
        poison(path)
        with pytest.raises(DatasetError, match=f"{path.name}: this cache changed since it was written"):
            train(dataclasses.replace(config, out=tmp_path / f"run-{next(runs)}"))
        path.write_bytes(original)

    def zero_the_tail(path):  # still a well-formed .npy: its last values zeroed
        path.write_bytes(path.read_bytes()[:-256] + bytes(256))

    def scale_the_weights(path):  # a well-formed read-out fit, its weights x1000
        payload = load_checkpoint(path, READOUT_KIND)
        payload["state_dict"] = {k: v * 1000 if v.is_floating_point() else v for k, v in payload["state_dict"].items()}
        save_checkpoint({k: v for k, v in payload.items() if k not in ("kind", "format_version")}, path, READOUT_KIND)

    def shift_the_objects(path):  # well-formed aux frames whose object state was moved
        with np.load(path, allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
        arrays["env_state"] = arrays["env_state"] + 1
        np.savez(path, **arrays)

    refused_when(features, zero_the_tail)
    refused_when(readout, scale_the_weights)
    readout.rename(tmp_path / "fit.pt")  # without the fit, the aux frames and their tokens are read
    refused_when(frames, shift_the_objects)
    refused_when(tokens, zero_the_tail)



def test_a_full_disk_ends_training_in_one_line_and_leaves_no_run_folder(run_inputs, tmp_path, monkeypatch):
    def full(fd):  # where a full disk shows for buffered writes: the data cannot be flushed
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "run"
    with pytest.raises(NoSpaceError, match=f"no space left on device while training into {out} .* free some space"):
        train(tiny_config(run_inputs, out, steps=2))
    assert not out.exists()  # its config.json could not be written: nothing of the run is left
    assert not [p for p in run_inputs[0].rglob("*") if p.name.endswith(".tmp")]


def test_a_full_disk_at_a_checkpoint_ends_in_one_line_and_a_resume_finishes(run_inputs, tmp_path, monkeypatch):
    """torchrl writes checkpoints through memory maps, where a full disk is SIGBUS: the space is claimed first."""
    out = tmp_path / "run"
    real = shutil.disk_usage

    def full_under_checkpoints(path):
        usage = real(path)
        return usage._replace(free=0) if "checkpoints" in pathlib.Path(path).parts else usage

    monkeypatch.setattr(shutil, "disk_usage", full_under_checkpoints)
    with pytest.raises(NoSpaceError, match=f"no space left on device while training into {out} .*--resume"):
        train(tiny_config(run_inputs, out, steps=8))
    monkeypatch.undo()
    (out / "checkpoints" / ".checkpoint-000000000004.killed.stage").mkdir()  # what a killed writer leaves
    assert train(tiny_config(run_inputs, out, steps=8, resume=True)).policy.is_file()
    assert not list((out / "checkpoints").glob(".*"))


def test_a_run_stored_with_retired_settings_resumes_at_their_value_only(run_inputs, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=4))
    path = out / "config.json"
    saved = json.loads(path.read_text())
    old = {**saved["config"], "aux_approach_fraction": 0.0, "aux_expert_displacement": 0.0, "readout_lr_decay": False,
           "policy": {**saved["config"]["policy"], "readout_coords": False}}
    path.write_text(json.dumps({**saved, "config": old}))  # as an earlier version wrote it
    (out / "policy.pt").unlink()
    assert train(tiny_config(run_inputs, out, steps=4, resume=True)).policy.is_file()
    for retired, value in (("aux_approach_fraction", 0.5), ("readout_lr_decay", True)):
        path.write_text(json.dumps({**saved, "config": {**old, retired: value}}))
        with pytest.raises(ConfigError, match=f"started with {retired} = {value}: a setting this version removed"):
            train(tiny_config(run_inputs, out, steps=4, resume=True))
    path.write_text(json.dumps({**saved, "config": {**old, "policy": {**old["policy"], "readout_coords": True}}}))
    with pytest.raises(ConfigError, match="started with policy.readout_coords = True: a setting this version removed"):
        train(tiny_config(run_inputs, out, steps=4, resume=True))


def test_a_policy_file_with_a_retired_setting_loads_at_its_value_only(run_inputs, tmp_path):
    from dust_rl.agents.factory import POLICY_KIND

    policy = train(tiny_config(run_inputs, tmp_path / "run", steps=2, readout="tokens", lambda_aux=1.0)).policy
    payload = {k: v for k, v in load_checkpoint(policy, POLICY_KIND).items() if k not in ("kind", "format_version")}
    for coords in (False, True):
        save_checkpoint({**payload, "config": {**payload["config"], "readout_coords": coords}}, policy, POLICY_KIND)
        if coords:
            with pytest.raises(CheckpointError, match="readout_coords = True: a setting this version removed"):
                load_policy(policy)
        else:
            assert load_policy(policy).config.readout == "tokens"


def test_keep_best_makes_policy_pt_the_evaluated_policy_of_the_highest_validation_success(tmp_path, capsys):
    for step, success in ((2, 0.5), (4, 0.25), (6, 0.5), (8, 0.0)):
        folder = tmp_path / "eval" / f"step-{step:07d}"
        folder.mkdir(parents=True)
        (folder / "report.json").write_text(json.dumps({"overall": {"success_rate": success}}))
        (folder / "policy.pt").write_bytes(f"policy of step {step}".encode())
    (tmp_path / "policy.pt").write_bytes(b"policy of step 8")
    _keep_best(tmp_path)
    assert (tmp_path / "policy.pt").read_bytes() == b"policy of step 6"  # the latest of the two best
    assert "step 6" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="give --logging.eval-every N"):
        LoggingSettings(keep_best=True)
