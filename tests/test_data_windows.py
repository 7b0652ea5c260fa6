"""Training windows checked against the raw episodes: chunks, padding at episode ends, future frames."""

from __future__ import annotations

import pytest
import torch

from dust_rl.data import DemoDataset
from dust_rl.data.windows import DemoWindows


def _expected_window(dataset: DemoDataset, row: int, horizon: int, offset: int) -> dict:
    """The window of ``row`` computed from its episode alone."""
    episode = int(dataset.data["episode"][row])
    rows = dataset.episode(episode)
    t = row - dataset.meta["episodes"][episode]["row_start"]
    last = rows.shape[0] - 1
    steps = [min(t + k, last) for k in range(horizon)]
    return {"chunk": rows["expert_action"][steps], "pad": torch.tensor([t + k > last for k in range(horizon)]),
            "image": rows["observation", "image", "front"][t], "instruction": rows["language_instruction"][t],
            "future_image": rows["observation", "image", "wrist"][min(t + offset, last)],
            "future_state": rows["observation", "state"][min(t + offset, last)], "clamped": t + offset > last}


@pytest.mark.parametrize("horizon,offset", [(5, 5), (8, 3), (1, 0)])
def test_full_iteration_matches_raw_episodes(demo_dir, horizon, offset):
    dataset = DemoDataset(demo_dir)
    windows = DemoWindows(dataset, horizon=horizon, future_offset=offset)
    seen = []
    for batch in windows.iterate(batch_size=16):
        assert batch["vla_action", "chunk"].shape[1:] == (horizon, dataset.meta["spec"]["action_dim"])
        assert batch["observation", "image", "front"].dtype == torch.uint8
        for i, row in enumerate(batch["index"].tolist()):
            expected = _expected_window(dataset, row, horizon, offset)
            assert torch.equal(batch["vla_action", "chunk"][i], expected["chunk"])
            assert torch.equal(batch["action_is_pad"][i], expected["pad"])
            assert torch.equal(batch["observation", "image", "front"][i], expected["image"])
            assert batch["language_instruction"][i] == expected["instruction"]
            assert torch.equal(batch["future", "observation", "image", "wrist"][i], expected["future_image"])
            assert torch.equal(batch["future", "observation", "state"][i], expected["future_state"])
            assert bool(batch["future", "is_clamped"][i]) == expected["clamped"]
        seen += batch["index"].tolist()
    assert seen == list(range(len(dataset)))  # every row once, in order


def test_sampled_windows_respect_episode_ends(demo_dir):
    dataset = DemoDataset(demo_dir)
    windows = DemoWindows(dataset, horizon=16, batch_size=32)
    torch.manual_seed(0)
    padded = 0
    for _ in range(5):
        batch = windows.sample()
        assert batch.batch_size == (32,)
        for i, row in enumerate(batch["index"].tolist()):
            expected = _expected_window(dataset, row, 16, 16)
            assert torch.equal(batch["vla_action", "chunk"][i], expected["chunk"])
            assert torch.equal(batch["action_is_pad"][i], expected["pad"])
            assert torch.equal(batch["future", "observation", "image", "wrist"][i], expected["future_image"])
        padded += int(batch["action_is_pad"].any(1).sum())
    assert padded > 0  # horizon 16 on 17-32 step episodes: windows near the end are sampled too


def test_epoch_sampling_without_replacement_covers_every_row(demo_dir):
    dataset = DemoDataset(demo_dir)
    windows = DemoWindows(dataset, horizon=4, batch_size=len(dataset), replacement=False)
    assert sorted(windows.sample()["index"].tolist()) == list(range(len(dataset)))


def test_invalid_window_sizes_are_refused(demo_dir):
    with pytest.raises(ValueError, match="horizon"):
        DemoWindows(DemoDataset(demo_dir), horizon=0)


def test_start_rows_take_the_requested_share_of_each_batch(demo_dir):
    dataset = DemoDataset(demo_dir)
    start_rows, fraction, draws = 2, 0.4, 4000
    windows = DemoWindows(dataset, horizon=4, batch_size=draws, images=False, start_rows=start_rows,
                          start_fraction=fraction)
    torch.manual_seed(0)
    batch = windows.sample()
    rows = batch["index"]
    steps = rows - dataset.episode_starts[dataset.data["episode"][rows]]
    for i in range(0, draws, 400):  # each drawn window is still that row's window
        assert torch.equal(batch["vla_action", "chunk"][i], _expected_window(dataset, int(rows[i]), 4, 4)["chunk"])
    share = (steps < start_rows).double().mean().item()
    sigma = (fraction * (1 - fraction) / draws) ** 0.5
    assert abs(share - fraction) < 5 * sigma  # binomial spread of the draw
    is_start = steps < start_rows
    assert len(set(rows[~is_start].tolist())) > 0.5 * (len(dataset) - start_rows * dataset.num_episodes)


@pytest.mark.parametrize("start_rows,fraction,replacement", [(2, 0.0, True), (0, 0.3, True), (2, 1.0, True),
                                                             (2, 0.3, False), (10_000, 0.3, True)])
def test_inconsistent_start_row_weighting_is_refused(demo_dir, start_rows, fraction, replacement):
    with pytest.raises(ValueError, match="start_rows"):
        DemoWindows(DemoDataset(demo_dir), horizon=4, start_rows=start_rows, start_fraction=fraction,
                    replacement=replacement)
