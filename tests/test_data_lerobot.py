"""LeRobot v3 export read back by torchrl's own LeRobot reader, and the export/import round trip."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from dust_rl.cli import main
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.video import read_mp4

IMAGE = ("observation", "image", "front")


@pytest.fixture(scope="module")
def export_dir(demo_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "export"
    main(["dataset", "export", str(demo_dir), "--format", "lerobot", "--out", str(out)])
    return out


def _as_offline_hub_snapshot(folder, hub, repo_id: str) -> None:
    """Lay ``folder`` out as a cached hub snapshot, which ``snapshot_download`` resolves offline."""
    commit = "0" * 40
    repo = hub / f"datasets--{repo_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    shutil.copytree(folder, repo / "snapshots" / commit)


def test_torchrl_reader_loads_the_export(demo_dir, export_dir, tmp_path, monkeypatch):
    for name, value in {"HF_HUB_CACHE": tmp_path / "hub", "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1",
                        "HF_DATASETS_CACHE": tmp_path / "hf_datasets"}.items():
        monkeypatch.setenv(name, str(value))
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_OFFLINE", True)
    _as_offline_hub_snapshot(export_dir, tmp_path / "hub", "dust-rl/demo")
    from torchrl.data.datasets import LeRobotExperienceReplay

    replay = LeRobotExperienceReplay("dust-rl/demo", root=tmp_path / "torchrl", download=True, batch_size=8,
                                     decode_video=False)
    loaded = replay._storage._storage
    dataset = DemoDataset(demo_dir)
    assert loaded.shape == (len(dataset),)
    assert torch.equal(loaded["action"], dataset.data["action"])
    assert torch.equal(loaded["expert_action"], dataset.data["expert_action"])
    assert torch.equal(loaded["observation", "state"], dataset.data["observation", "state"])
    assert torch.equal(loaded["episode"], dataset.data["episode"])
    assert list(loaded["language_instruction"]) == [dataset.instructions[i] for i in dataset.data["instruction_index"]]
    assert torch.equal(loaded["next", "done"], dataset.data["next", "done"])
    # Video references point each row at its frame of our MP4; decoding that frame gives the image back.
    ref = loaded["observation", "image", "front"]
    assert torch.equal(ref.frame_index, torch.arange(len(dataset)))
    frames = np.stack(list(read_mp4(ref.sources[0] if isinstance(ref.sources, (list, tuple)) else ref.sources)))
    decoded = torch.from_numpy(frames).permute(0, 3, 1, 2).float()
    assert (decoded - dataset.data[IMAGE].float()).abs().mean() < 8
    assert len(replay.sample()) == 8


def test_import_round_trip(demo_dir, export_dir, tmp_path):
    main(["dataset", "import", str(export_dir), "--out", str(tmp_path / "back")])
    original, back = DemoDataset(demo_dir), DemoDataset(tmp_path / "back")
    assert (back.data.exclude("observation") == original.data.exclude("observation")).all()
    assert torch.equal(back.data["observation", "state"], original.data["observation", "state"])
    assert torch.equal(back.data["observation", "environment_state"], original.data["observation", "environment_state"])
    error = (back.data[IMAGE].float() - original.data[IMAGE].float()).abs().mean()
    assert error < 8, f"H.264 round trip drifted by {error:.1f} grey levels on average"
    for key in ("episodes", "instructions", "tasks", "spec", "env_id", "env_kwargs", "environment_state_dims"):
        assert back.meta[key] == original.meta[key], key
    assert back.meta["source"].startswith("lerobot:")


def test_export_refuses_an_existing_folder_and_import_a_damaged_one(demo_dir, export_dir, tmp_path):
    with pytest.raises(SystemExit, match="already exists"):
        main(["dataset", "export", str(demo_dir), "--out", str(export_dir)])
    damaged = tmp_path / "damaged"
    shutil.copytree(export_dir, damaged)
    (damaged / "meta" / "info.json").write_text("{not json")
    with pytest.raises(DatasetError, match="info.json"):
        from dust_rl.data.lerobot_import import import_lerobot
        import_lerobot(damaged, tmp_path / "out")
    assert not (tmp_path / "out").exists()
