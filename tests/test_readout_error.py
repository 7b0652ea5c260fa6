"""experiments/readout_error.py's table: per step bucket, the distances it names, on a real dataset."""

from __future__ import annotations

import importlib.util
import pathlib

import torch

from dust_rl.agents import make_policy
from dust_rl.data import DemoDataset
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.keys import ENV_STATE_KEY

_SPEC = importlib.util.spec_from_file_location(
    "readout_error", pathlib.Path(__file__).parents[1] / "experiments" / "readout_error.py")
readout_error = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(readout_error)
STEP_BUCKETS, TARGET_XY, readout_error_table = (readout_error.STEP_BUCKETS, readout_error.TARGET_XY,
                                                readout_error.readout_error_table)


def test_a_read_out_that_always_says_the_mean_is_as_far_off_as_the_mean_is(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         aux_state_dim=env_state_width(dataset), lambda_aux=1.0)
    last = policy.state_readout.pool.head[-1]
    with torch.no_grad():  # estimate 0 in normalised units: the training mean, whatever the image
        last.weight.zero_()
        last.bias.zero_()
    norm = EnvStateNorm.of_dataset(dataset)
    table = readout_error_table(policy, dataset, norm).splitlines()
    target = dataset.data.get(ENV_STATE_KEY)[:, TARGET_XY].float()
    mean = norm.mean[dataset.row_task_index][:, TARGET_XY]  # each row's task's mean
    step = torch.arange(len(dataset)) - torch.repeat_interleave(dataset.episode_starts, dataset.lengths)
    rows = table[2:]
    filled = [(low, high) for low, high in STEP_BUCKETS if ((step >= low) & (step < high)).any()]
    assert len(rows) == len(filled)
    for row, (low, high) in zip(rows, filled):
        cells = [c.strip() for c in row.strip("|").split("|")]
        m = (step >= low) & (step < high)
        assert int(cells[1]) == int(m.sum())
        expected = 100 * (target[m] - mean[m]).norm(dim=1).mean().item()
        assert abs(float(cells[2]) - expected) <= 0.05 + 1e-6  # printed to 0.1 cm
