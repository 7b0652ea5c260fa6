"""Data-parallel training (``--runtime.nproc``): two gloo processes on this CPU against one process."""

from __future__ import annotations

import csv
import shutil

import pytest
import torch
from conftest import rounding_tolerance
from test_train import tiny_config, trained_weights

from dust_rl.agents import save_image_encoder
from dust_rl.agents.model.flow_matching import Shard, cpu_drawn, sample_tau
from dust_rl.cli import main
from dust_rl.errors import ConfigError
from dust_rl.train.imitation import train

pytestmark = pytest.mark.usefixtures("one_thread")

# Action-only with one-step chunks: no padded action and no future, so each rank's mean loss over its
# slice is exactly its share of the global batch's mean, and two processes must reproduce one.
NO_PADDING = {"variant": "action_only", "horizon": 1, "execute_steps": 1}


@pytest.fixture(scope="module")
def run_inputs(demo_dir, tmp_path_factory):
    from dust_rl.agents import AutoencoderConfig, ConvAutoencoder

    root = tmp_path_factory.mktemp("ddp")
    dataset = shutil.copytree(demo_dir, root / "data")
    encoder = ConvAutoencoder(AutoencoderConfig(image_size=32, dim=16, width=8, max_width=16))
    return dataset, save_image_encoder(encoder, root / "encoder.pt")


def logged_losses(out) -> list[tuple[int, float]]:
    with open(out / "logs" / "train" / "scalars" / "train" / "loss.csv") as file:
        return [(int(step), float(value)) for step, value in csv.reader(file)]


def test_shard_draws_are_the_whole_batch_split():
    whole = [torch.Generator().manual_seed(3) for _ in range(2)]
    expected = torch.randn(6, 2, generator=whole[0]), sample_tau(6, generator=whole[0])
    for index in range(2):
        generator = torch.Generator().manual_seed(3)
        shard = Shard(index, 2)
        part = cpu_drawn(torch.randn, 3, 2, generator=generator, shard=shard), sample_tau(3, generator=generator,
                                                                                          shard=shard)
        assert torch.equal(part[0], expected[0][shard.rows(6)])
        assert torch.equal(part[1], expected[1][shard.rows(6)])
    with pytest.raises(ValueError, match="evenly"):
        Shard(0, 2).rows(5)
    with pytest.raises(ValueError, match="index"):
        Shard(2, 2)


@pytest.mark.parametrize("variant", ["action_only", "dust"])
def test_two_processes_train_like_one(run_inputs, tmp_path, variant):
    """Both ranks end with identical weights (the run compares them at its end and raises otherwise); without
    padding (action-only), every logged loss is the one-process loss of the same global batch up to rounding."""
    settings = NO_PADDING if variant == "action_only" else {"variant": variant}
    train(tiny_config(run_inputs, tmp_path / "one", steps=3, log_every=1, **settings))
    train(tiny_config(run_inputs, tmp_path / "two", steps=3, log_every=1, nproc=2, **settings))
    assert (tmp_path / "two" / "policy.pt").is_file()
    assert sorted(p.name for p in (tmp_path / "two" / "checkpoints").iterdir()) == \
        sorted(p.name for p in (tmp_path / "one" / "checkpoints").iterdir())
    one, two = logged_losses(tmp_path / "one"), logged_losses(tmp_path / "two")
    assert [step for step, _ in one] == [step for step, _ in two] == [1, 2, 3]
    if variant == "action_only":  # an 8-window mean of 8 action dimensions, computed in two halves
        for (step, expected), (_, actual) in zip(one, two, strict=True):
            assert abs(actual - expected) <= rounding_tolerance(torch.float32, 8 * 8, depth=step, scale=expected)


def test_nproc_resume_ends_like_uninterrupted(run_inputs, tmp_path):
    """A 2-process run stopped after its first checkpoint and resumed ends with the weights of one never stopped."""
    straight = tiny_config(run_inputs, tmp_path / "straight", steps=4, checkpoint_every=2, nproc=2, **NO_PADDING)
    train(straight)
    first = tiny_config(run_inputs, tmp_path / "resumed", steps=4, checkpoint_every=2, nproc=2, **NO_PADDING)
    train(first)
    shutil.rmtree(max((tmp_path / "resumed" / "checkpoints").iterdir()))  # as if stopped after step 2
    (tmp_path / "resumed" / "policy.pt").unlink()
    resumed = tiny_config(run_inputs, tmp_path / "resumed", steps=4, checkpoint_every=2, nproc=2, resume=True,
                          **NO_PADDING)
    train(resumed)
    a, b = trained_weights(tmp_path / "straight" / "policy.pt"), trained_weights(tmp_path / "resumed" / "policy.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_nproc_refuses_what_it_cannot_split(run_inputs, tmp_path):
    with pytest.raises(ConfigError, match="evenly"):
        tiny_config(run_inputs, tmp_path / "odd", batch_size=7, nproc=2)
    with pytest.raises(ConfigError, match="video_dataset"):
        tiny_config(run_inputs, tmp_path / "video", nproc=2, video_dataset=run_inputs[0])
    with pytest.raises(ConfigError, match="nproc"):
        tiny_config(run_inputs, tmp_path / "zero", nproc=0)


def test_a_failing_process_ends_the_command_with_its_error(tmp_path):
    with pytest.raises(SystemExit, match=r"dust-rl: error: a process of the 2-process run failed: .*no meta\.json"):
        main(["train", "--dataset", str(tmp_path / "missing"), "--out", str(tmp_path / "run"), "--runtime.nproc", "2"])
