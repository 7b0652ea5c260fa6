"""LeRobot v3 export read back by torchrl's own LeRobot reader, the export/import round trip, and the import
of LeRobot datasets written by others (no dust-rl metadata) for an env given on the command line."""

from __future__ import annotations

import json
import shutil

import gymnasium as gym
import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from test_train import tiny_policy

from dust_rl.agents import load_policy, save_image_encoder
from dust_rl.cli import main
from dust_rl.data import DatasetError, DemoDataset, DemoWindows
from dust_rl.data.lerobot_export import DATA_FILE, EPISODES_FILE
from dust_rl.data.lerobot_import import import_lerobot
from dust_rl.data.video import read_mp4
from dust_rl.errors import ConfigError
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.settings import LoggingSettings, OptimSettings, TrainRuntime

IMAGE = ("observation", "image", "front")
# The per-frame features any LeRobot v3 dataset has (besides its videos); no dust-rl extras.
PLAIN_FEATURES = ("observation.state", "action", "timestamp", "frame_index", "episode_index", "index", "task_index")
PLAIN_IMPORT = ["--env", "DustFranka-v0", "--task", "press_button", "--image-size", "32"]


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


def test_every_exported_feature_has_a_dtype_a_shape_and_names(export_dir):
    features = json.loads((export_dir / "meta" / "info.json").read_text())["features"]
    assert all({"dtype", "shape", "names"} <= set(feature) for feature in features.values())
    state = features["observation.state"]["names"]
    assert len(state) == features["observation.state"]["shape"][0] == 17
    assert state[:1] + state[7:10] + state[-1:] == ["panda/joint1", "panda/finger_joint1", "panda/finger_joint2",
                                                    "pinch.x", "pinch.opening"]
    expected_action = ["pinch.x", "pinch.y", "pinch.z", "pinch.rx", "pinch.ry", "pinch.rz", "pinch.closure"]
    assert features["action"]["names"] == features["expert_action"]["names"] == expected_action
    env_state = features["observation.environment_state"]
    assert env_state["names"] == [f"environment_state_{i}" for i in range(env_state["shape"][0])]
    for camera in ("front", "wrist"):  # LeRobot's key, the frame's layout named dimension by dimension
        image = features[f"observation.images.{camera}"]
        assert (image["shape"], image["names"]) == ([32, 32, 3], ["height", "width", "channels"])
    assert features["next.reward"]["names"] is None  # scalars, as LeRobot's own index columns


def _rename_videos(root, old: str, new: str) -> None:
    """Move every video feature of the LeRobot folder ``root`` from the key prefix ``old`` to ``new``."""
    info = json.loads((root / "meta" / "info.json").read_text())
    info["features"] = {name.replace(old, new, 1): feature for name, feature in info["features"].items()}
    (root / "meta" / "info.json").write_text(json.dumps(info))
    for folder in list((root / "videos").iterdir()):
        folder.rename(folder.with_name(folder.name.replace(old, new, 1)))
    episodes = pq.read_table(root / EPISODES_FILE)
    pq.write_table(episodes.rename_columns([name.replace(f"videos/{old}", f"videos/{new}", 1)
                                            for name in episodes.column_names]), root / EPISODES_FILE)


@pytest.mark.parametrize("edit", ["env-image-keys", "previous-version"])
def test_import_reads_the_env_image_keys_and_exports_without_names(demo_dir, export_dir, tmp_path, edit):
    """Video features under the env's ``observation.image.<camera>`` keys, and an export of the previous version
    (no feature names), import as the export itself does."""
    copy = shutil.copytree(export_dir, tmp_path / "copy")
    if edit == "env-image-keys":
        _rename_videos(copy, "observation.images.", "observation.image.")
    else:
        info = json.loads((copy / "meta" / "info.json").read_text())
        for feature in info["features"].values():
            feature["names"] = ["height", "width", "channels"] if feature["dtype"] == "video" else None
        (copy / "meta" / "info.json").write_text(json.dumps(info))
    import_lerobot(copy, tmp_path / "back", progress=False)
    original, back = DemoDataset(demo_dir), DemoDataset(tmp_path / "back")
    assert torch.equal(back.data["observation", "state"], original.data["observation", "state"])
    for camera in ("front", "wrist"):
        key = ("observation", "image", camera)
        assert (back.data[key].float() - original.data[key].float()).abs().mean() < 8


def test_export_refuses_an_existing_folder_and_import_a_damaged_one(demo_dir, export_dir, tmp_path):
    with pytest.raises(SystemExit, match="already exists"):
        main(["dataset", "export", str(demo_dir), "--out", str(export_dir)])
    damaged = tmp_path / "damaged"
    shutil.copytree(export_dir, damaged)
    (damaged / "meta" / "info.json").write_text("{not json")
    with pytest.raises(DatasetError, match="info.json"):
        import_lerobot(damaged, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def as_plain_lerobot(export, out, edit_info=lambda info: None):
    """A copy of our export as another LeRobot v3 writer leaves it: no dust_rl.json, no dust-rl columns."""
    shutil.copytree(export, out)
    (out / "meta" / "dust_rl.json").unlink()
    info = json.loads((out / "meta" / "info.json").read_text())
    info["features"] = {name: feature for name, feature in info["features"].items()
                        if name in PLAIN_FEATURES or feature["dtype"] == "video"}
    edit_info(info)
    (out / "meta" / "info.json").write_text(json.dumps(info))
    data = pq.read_table(out / DATA_FILE)
    pq.write_table(data.select([name for name in data.column_names if name in PLAIN_FEATURES]), out / DATA_FILE)
    episodes = pq.read_table(out / EPISODES_FILE)
    pq.write_table(episodes.select([name for name in episodes.column_names if not name.startswith("dust_rl/")]),
                   out / EPISODES_FILE)
    return out


@pytest.fixture(scope="module")
def plain_import(export_dir, tmp_path_factory):
    """A plain LeRobot copy of the demo export, and its import for DustFranka-v0 press_button at 32 px."""
    root = tmp_path_factory.mktemp("plain")
    plain = as_plain_lerobot(export_dir, root / "plain")
    main(["dataset", "import", str(plain), "--out", str(root / "imported"), *PLAIN_IMPORT])
    return plain, root / "imported"


def test_a_plain_lerobot_dataset_imports_for_the_env_it_fits(demo_dir, plain_import, tmp_path):
    plain, imported = plain_import
    with pytest.raises(DatasetError, match="no meta/dust_rl.json .* give the env"):
        import_lerobot(plain, tmp_path / "out")
    with pytest.raises(ConfigError, match="--task"):
        import_lerobot(plain, tmp_path / "out", env_id="DustFranka-v0")
    assert not (tmp_path / "out").exists()

    original = DemoDataset(demo_dir)
    back = DemoDataset(imported, env=gym.make("DustFranka-v0", task="press_button", image_size=32))
    for key in (("observation", "state"), "action", "frame_index", "instruction_index", ("next", "done")):
        assert torch.equal(back.data[key], original.data[key]), key
    assert torch.equal(back.data["expert_action"], original.data["action"])  # the demonstrator's action is the label
    assert back.data["observation", "environment_state"].shape == (len(original), 0)
    assert torch.equal(back.data["next", "terminated"], back.data["next", "done"])
    assert not back.data["next", "truncated"].any() and not back.data["next", "reward"].any()
    assert [e["length"] for e in back.meta["episodes"]] == [e["length"] for e in original.meta["episodes"]]
    assert back.instructions == original.instructions and back.tasks == ["press_button"]
    assert (back.meta["env_id"], back.meta["env_kwargs"]) == ("DustFranka-v0", {"image_size": 32})
    assert (back.data[IMAGE].float() - original.data[IMAGE].float()).abs().mean() < 8  # H.264, as in the round trip


def test_training_runs_on_a_plain_lerobot_import(plain_import, tiny_encoder, tmp_path):
    _, imported = plain_import
    windows = DemoWindows(DemoDataset(imported), horizon=4, batch_size=8)
    assert windows.sample()["vla_action", "chunk"].shape == (8, 4, 7)
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    result = train(TrainConfig(dataset=imported, out=tmp_path / "run", policy=tiny_policy(encoder),
                               optim=OptimSettings(steps=2, batch_size=8),
                               logging=LoggingSettings(log_every=1, checkpoint_every=2),
                               runtime=TrainRuntime(threads=1, progress=False)))
    assert np.isfinite(result.final_loss)
    policy = load_policy(result.policy)
    assert policy.info["env_id"] == "DustFranka-v0" and policy.info["tasks"] == ["press_button"]


def test_video_features_may_list_their_channels_first(export_dir, tmp_path):
    def channels_first(info):
        for camera in ("front", "wrist"):
            info["features"][f"observation.images.{camera}"].update(shape=[3, 32, 32],
                                                                     names=["channels", "height", "width"])

    plain = as_plain_lerobot(export_dir, tmp_path / "plain", channels_first)
    import_lerobot(plain, tmp_path / "out", env_id="DustFranka-v0", task="press_button", env_kwargs={"image_size": 32},
                   progress=False)
    assert DemoDataset(tmp_path / "out").data[IMAGE].shape[1:] == (3, 32, 32)


def _drop_wrist(info):
    del info["features"]["observation.images.wrist"]


def _state_of_5(info):
    info["features"]["observation.state"]["shape"] = [5]


def _no_action(info):
    del info["features"]["action"]


def _fps_30(info):
    info["fps"] = 30


@pytest.mark.parametrize("edit_info,args,problem", [
    (lambda info: None, ["--image-size", "48"],
     r"observation\.images\.front: shape \[32, 32, 3\], the env renders \[48, 48, 3\] \(set the env's image_size\)"),
    (_drop_wrist, [], r"observation\.images\.wrist: missing \(the env has cameras \['front', 'wrist'\]"),
    (_state_of_5, [], r"observation\.state: shape \[5\], the env has \[17\]"),
    (_no_action, [], r"action: missing"),
    (_fps_30, [], r"fps: dataset records 30 frames/s, the env has fps 20"),
], ids=["image-size", "camera", "state", "action", "fps"])
def test_import_names_the_feature_that_does_not_fit_the_env(export_dir, tmp_path, edit_info, args, problem):
    plain = as_plain_lerobot(export_dir, tmp_path / "plain", edit_info)
    with pytest.raises(SystemExit, match=problem) as error:
        main(["dataset", "import", str(plain), "--out", str(tmp_path / "out"), *PLAIN_IMPORT, *args])
    assert "\n" not in str(error.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("edit,problem", [
    ({"env_id": "CartPole-v1"}, r"unknown env id 'CartPole-v1'; dust-rl registers \['DustFranka-v0'"),
    ({"env_kwargs": {"image_size": 100000}}, r"image_size must be an int in \[1, 1024\].*got 100000"),
    ({"env_kwargs": {"image_size": 32, "control_hz": 10.0}}, r"does not match its env \(control_hz: dataset has 20"),
], ids=["not-a-dust-env", "huge-images", "other-spec"])
def test_import_refuses_a_dust_rl_json_naming_another_env(export_dir, tmp_path, edit, problem):
    source = shutil.copytree(export_dir, tmp_path / "source")
    meta_file = source / "meta" / "dust_rl.json"
    meta_file.write_text(json.dumps(json.loads(meta_file.read_text()) | edit))
    with pytest.raises(SystemExit, match=problem) as error:
        main(["dataset", "import", str(source), "--out", str(tmp_path / "out")])
    assert "\n" not in str(error.value)
    assert not (tmp_path / "out").exists()
