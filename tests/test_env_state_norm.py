"""Per-task object-state normalisation: every task's own columns at zero mean and unit spread, padding at 0."""

from __future__ import annotations

import pytest
import torch
from conftest import DEMO_ENV_KWARGS, rounding_tolerance

from dust_rl.agents import make_policy
from dust_rl.agents.normalizer import MIN_STD
from dust_rl.data import DemoDataset
from dust_rl.data.collect import collect_demos
from dust_rl.data.env_state_norm import INFO_KEY, PER_TASK, EnvStateNorm
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.keys import ENV_STATE_KEY


def test_rows_know_their_task(demo_dir):
    dataset = DemoDataset(demo_dir)
    for episode in dataset.meta["episodes"]:
        rows = dataset.row_task_index[episode["row_start"]:episode["row_start"] + episode["length"]]
        assert rows.eq(dataset.tasks.index(episode["task"])).all()
    assert len(dataset.row_task_index) == len(dataset)


def test_each_task_is_normalised_by_its_own_rows_over_its_own_columns(demo_dir):
    dataset = DemoDataset(demo_dir)
    assert len(dataset.tasks) > 1 and len(set(dataset.meta["environment_state_dims"].values())) > 1
    norm = EnvStateNorm.of_dataset(dataset)
    states = dataset.data.get(ENV_STATE_KEY).float()
    normalised = norm.normalize(states, dataset.row_task_index)
    for index, task in enumerate(dataset.tasks):
        width = dataset.meta["environment_state_dims"][task]
        rows = states[dataset.row_task_index == index].double()
        expected = (rows - rows.mean(0)) / rows.std(0, correction=0).clamp_min(MIN_STD)
        expected[:, width:] = 0.0  # the padding stays 0
        # float32 subtraction of values |x| apart by std: rounding of x relative to the task's spread.
        atol = rounding_tolerance(torch.float32, len(rows), scale=(rows.abs() / norm.std[index].double()).max().item())
        torch.testing.assert_close(normalised[dataset.row_task_index == index].double(), expected, rtol=0, atol=atol)
        torch.testing.assert_close(norm.denormalize(normalised, dataset.row_task_index)[:, :width],
                                   states[:, :width], rtol=0, atol=atol * norm.std.max().item())


def test_a_single_task_dataset_keeps_its_meta_statistics(tmp_path):
    root = tmp_path / "one"
    collect_demos(root, tasks=["open_drawer"], episodes=1, env_kwargs=DEMO_ENV_KWARGS, progress=False)
    dataset = DemoDataset(root)
    stats = dataset.meta["stats"]["observation.environment_state"]
    norm = EnvStateNorm.of_dataset(dataset)
    assert torch.equal(norm.mean[0], torch.tensor(stats["mean"]))
    assert torch.equal(norm.std[0], torch.tensor(stats["std"]).clamp_min(MIN_STD))


def test_pooled_statistics_and_unknown_tasks(demo_dir):
    dataset = DemoDataset(demo_dir)
    pooled = EnvStateNorm.of_dataset(dataset, per_task=False)
    stats = dataset.meta["stats"]["observation.environment_state"]
    assert all(torch.equal(row, torch.tensor(stats["mean"])) for row in pooled.mean)
    assert torch.equal(pooled.task_indices(list(reversed(dataset.tasks))), torch.tensor([1, 0]))
    with pytest.raises(ValueError, match="no object-state statistics for \\['stack'\\]"):
        pooled.task_indices(["stack"])


def test_a_policy_names_the_normalisation_it_was_trained_with(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         aux_state_dim=env_state_width(dataset), lambda_aux=1.0)
    policy.info = {"dataset": str(demo_dir)}  # trained before per-task statistics: the pooled ones
    assert torch.equal(EnvStateNorm.of_policy(policy).mean, EnvStateNorm.of_dataset(dataset, per_task=False).mean)
    policy.info[INFO_KEY] = PER_TASK
    assert torch.equal(EnvStateNorm.of_policy(policy).mean, EnvStateNorm.of_dataset(dataset).mean)
