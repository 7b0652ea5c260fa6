"""Files from elsewhere stay inert: datasets never unpickle, paths in metadata stay in their folder,
crafted LeRobot folders are refused, and policy files can neither ask for absurd sizes nor a download.

Each crafted pickle here would create a marker file when unpickled; every test checks that it never
appears, besides the one-line error naming the offending file.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from crafted import CRAFTS, edit_json

from dust_rl.agents import (
    VARIANTS,
    DustConfig,
    DustModel,
    PolicyConfig,
    load_policy,
    make_policy,
    save_policy,
)
from dust_rl.agents.encoders.hf_vision import build_transformers_config
from dust_rl.cli import main
from dust_rl.data import DatasetError, DemoDataset, collect_demos
from dust_rl.data.lerobot_export import EPISODES_FILE
from dust_rl.data.video import write_mp4
from dust_rl.errors import CheckpointError
from dust_rl.storage.memmap_io import check_memmap_dir
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.settings import OptimSettings, TrainRuntime

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture
def copy(demo_dir, tmp_path):
    return shutil.copytree(demo_dir, tmp_path / "ds")


@pytest.fixture
def marker(tmp_path):
    return tmp_path / "code-ran"


def _data_dir(root: pathlib.Path) -> pathlib.Path:
    return root / json.loads((root / "meta.json").read_text())["data"]


def _read_with(entry: str, root: pathlib.Path, tmp_path: pathlib.Path, encoder: pathlib.Path) -> None:
    """Read the dataset at ``root`` the way one of the package's entry points does."""
    if entry == "train":
        train(TrainConfig(dataset=root, out=tmp_path / "run", policy=PolicyConfig(image_encoder=str(encoder)),
                          optim=OptimSettings(steps=1), runtime=TrainRuntime(threads=1, progress=False)))
    elif entry == "collect-resume":  # one more episode, then the consolidated rows are read back
        collect_demos(root, tasks=["press_button"], episodes=4, env_kwargs={"image_size": 32}, progress=False)
    else:
        main({"info": ["dataset", "info", str(root)],
              "video": ["dataset", "video", str(root), "--out", str(tmp_path / "grid.mp4")],
              "export": ["dataset", "export", str(root), "--out", str(tmp_path / "export")],
              "pretrain-encoder": ["pretrain-encoder", "--dataset", str(root), "--out", str(tmp_path / "enc.pt"),
                                   "--steps", "1"]}[entry])


@pytest.mark.parametrize("craft", CRAFTS)
@pytest.mark.parametrize("entry", ["info", "video", "export", "pretrain-encoder", "train", "collect-resume"])
def test_a_pickle_in_a_dataset_never_runs(copy, marker, tmp_path, tiny_encoder, craft, entry):
    from dust_rl.agents import save_image_encoder

    named = CRAFTS[craft](_data_dir(copy), marker)
    encoder = save_image_encoder(tiny_encoder, tmp_path / "tiny.pt")
    with pytest.raises((DatasetError, SystemExit), match=re.escape(str(named))) as error:
        _read_with(entry, copy, tmp_path, encoder)
    assert "not a tensor" in str(error.value) or "not a TensorDict of tensors" in str(error.value)
    assert "\n" not in str(error.value)
    assert not marker.exists()


@pytest.mark.parametrize("field", [{"dtype": "torch.load"}, {"device": "os.system('x')"}, {"is_nested": True}])
def test_only_whole_tensors_of_known_dtypes_are_read(copy, field):
    data = _data_dir(copy)
    entry = json.loads((data / "meta.json").read_text())["action"]
    edit_json(data / "meta.json", action=entry | field)
    with pytest.raises(DatasetError, match=r"entry 'action' is not a plain tensor of a known dtype"):
        DemoDataset(copy)


@pytest.mark.parametrize("device", ["cuda:0", "cuda", "mps"])
def test_tensors_recorded_on_an_accelerator_pass_the_check(copy, device):
    """A checkpoint written during GPU training records ``cuda:0`` for its tensors: a device name, not code."""
    data = _data_dir(copy)
    edit_json(data / "meta.json", action=json.loads((data / "meta.json").read_text())["action"] | {"device": device})
    check_memmap_dir(data)


@pytest.mark.parametrize("where", ["parent", "absolute", "symlink"])
def test_the_data_folder_named_in_meta_stays_inside_the_dataset(copy, tmp_path, where):
    outside = shutil.copytree(_data_dir(copy), tmp_path / "elsewhere")  # a whole, loadable data folder
    name = {"parent": "../elsewhere", "absolute": str(outside), "symlink": "data-link"}[where]
    if where == "symlink":
        os.symlink(outside, copy / "data-link")
    edit_json(copy / "meta.json", data=name)
    with pytest.raises(DatasetError, match=r"meta\.json: path .* (leaves the dataset folder|is a symlink out)"):
        DemoDataset(copy)


def test_a_data_file_linked_out_of_the_dataset_is_refused(copy, tmp_path):
    action = _data_dir(copy) / "action.memmap"
    outside = shutil.copy(action, tmp_path / "action.memmap")
    action.unlink()
    os.symlink(outside, action)
    with pytest.raises(DatasetError, match=r"'action\.memmap' is a symlink out"):
        DemoDataset(copy)


def test_episode_folders_stay_inside_the_dataset_on_resume(copy, tmp_path):
    victim = shutil.copytree(copy / "episodes" / "press_button", tmp_path / "victim")
    victim_files = sorted(victim.rglob("*"))
    record = copy / "episodes" / "press_button" / "seed-000000" / "episode.json"
    edit_json(record, task="../../../victim")  # its rows would be read, then deleted, out of the dataset
    with pytest.raises(DatasetError, match=r"seed-000000: episode record names task '\.\./\.\./\.\./victim'"):
        collect_demos(copy, tasks=["press_button"], episodes=3, env_kwargs={"image_size": 32}, progress=False)
    shutil.rmtree(copy / "episodes" / "press_button")
    os.symlink(victim, copy / "episodes" / "press_button")
    with pytest.raises(DatasetError, match=r"episodes/press_button/seed-000000' is a symlink out"):
        collect_demos(copy, tasks=["press_button"], episodes=3, env_kwargs={"image_size": 32}, progress=False)
    assert sorted(victim.rglob("*")) == victim_files


# -- crafted LeRobot folders ---------------------------------------------------------------------------------


@pytest.fixture
def lerobot(export_dir, tmp_path):
    return shutil.copytree(export_dir, tmp_path / "lerobot")


def _edit_episodes(root: pathlib.Path, column: str, row: int, value) -> None:
    table = pq.read_table(root / EPISODES_FILE)
    values = table.column(column).to_pylist()
    values[row] = value
    index = table.column_names.index(column)
    pq.write_table(table.set_column(index, column, pa.array(values, table.schema.field(column).type)),
                   root / EPISODES_FILE)


def _video_outside(root: pathlib.Path, tmp_path: pathlib.Path, template: str) -> None:
    """Move the videos out of the folder and point ``video_path`` at them (the old reader followed it)."""
    shutil.move(root / "videos", tmp_path / "videos")
    edit_json(root / "meta" / "info.json", video_path=template.format(outside=tmp_path))


def _video_of_another_size(root: pathlib.Path, tmp_path: pathlib.Path) -> None:
    video = root / "videos" / "observation.images.front" / "chunk-000" / "file-000.mp4"
    write_mp4(video, [np.zeros((48, 64, 3), np.uint8)] * 5, fps=20)


def _symlinked_video(root: pathlib.Path, tmp_path: pathlib.Path) -> None:
    video = root / "videos" / "observation.images.front" / "chunk-000" / "file-000.mp4"
    outside = shutil.move(video, tmp_path / "front.mp4")
    os.symlink(outside, video)


LEROBOT_CRAFTS = {
    "absolute-video-path": (lambda root, tmp: _video_outside(
        root, tmp, "{outside}/videos/{{video_key}}/chunk-{{chunk_index:03d}}/file-{{file_index:03d}}.mp4"),
        r"path '/.*' leaves the dataset folder"),
    "parent-video-path": (lambda root, tmp: _video_outside(
        root, tmp, "../videos/{{video_key}}/chunk-{{chunk_index:03d}}/file-{{file_index:03d}}.mp4"),
        r"path '\.\./videos/.*' leaves the dataset folder"),
    "attribute-in-video-path": (lambda root, tmp: edit_json(
        root / "meta" / "info.json", video_path="videos/{video_key.__class__.__init__}/file.mp4"),
        r"uses \{video_key\.__class__\.__init__\}; only \{video_key\}"),
    "symlinked-video": (_symlinked_video, r"file-000\.mp4' is a symlink out"),
    "video-of-another-size": (_video_of_another_size, r"file-000\.mp4: frames are 48x64, expected 32x32"),
    "negative-length": (lambda root, tmp: _edit_episodes(root, "length", 1, -5),
                        r"episode 1 has length -5; episodes need at least one frame"),
    "overlap": (lambda root, tmp: _edit_episodes(root, "dataset_from_index", 1, 3) or _edit_episodes(
        root, "length", 1, pq.read_table(root / EPISODES_FILE).column("dataset_to_index")[1].as_py() - 3),
        r"episodes 0 and 1 overlap"),
    "out-of-range": (lambda root, tmp: _edit_episodes(root, "dataset_to_index", 5, 10_000) or _edit_episodes(
        root, "length", 5, 10_000 - pq.read_table(root / EPISODES_FILE).column("dataset_from_index")[5].as_py()),
        r"episode 5 spans frames \d+\.\.10000 .* outside the \d+ frames"),
    "empty-dust-json": (lambda root, tmp: (root / "meta" / "dust_rl.json").write_text(""),
                        r"dust_rl\.json: unreadable"),
    "dust-json-list": (lambda root, tmp: (root / "meta" / "dust_rl.json").write_text("[1, 2]"),
                       r"dust_rl\.json: expected a JSON object, got list"),
    "dust-json-without-keys": (lambda root, tmp: (root / "meta" / "dust_rl.json").write_text("{}"),
                               r"dust_rl\.json: missing or malformed \['env_id', 'env_kwargs', 'spec'"),
    "dust-json-wrong-state": (lambda root, tmp: edit_json(root / "meta" / "dust_rl.json", spec={
        **json.loads((root / "meta" / "dust_rl.json").read_text())["spec"], "state_dim": 5}),
        r"observation\.state: shape \[17\], meta/dust_rl\.json has \[5\]"),
}


@pytest.mark.parametrize("craft", LEROBOT_CRAFTS)
def test_a_crafted_lerobot_folder_is_refused_and_leaves_nothing(lerobot, tmp_path, craft):
    edit, problem = LEROBOT_CRAFTS[craft]
    edit(lerobot, tmp_path)
    outside_before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(SystemExit, match=problem) as error:
        main(["dataset", "import", str(lerobot), "--out", str(tmp_path / "out")])
    assert "\n" not in str(error.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == outside_before  # no output, no temporary left behind


# -- policy files ------------------------------------------------------------------------------------------


@pytest.fixture(params=["policy.pt", "policy"], ids=["file", "folder"])
def policy_file(tiny_encoder, minilm, tmp_path, request):
    """A tiny policy saved as one torch file or as a folder of config.json and model.safetensors."""
    policy = make_policy("dust", image_encoder=tiny_encoder, text_encoder=minilm, cameras=["front"], action_dim=3,
                         state_dim=5, horizon=4, d_model=32, n_heads=2, n_mmdit=2, n_dit=0)
    return save_policy(policy, tmp_path / request.param)


def _crafted(path: pathlib.Path, edit) -> pathlib.Path:
    """A copy of the policy at ``path`` (file or folder) named ``crafted``, its entries changed by ``edit``."""
    if path.is_dir():
        crafted = shutil.copytree(path, path.with_name("crafted"))
        payload = json.loads((crafted / "config.json").read_text())
        edit(payload)
        (crafted / "config.json").write_text(json.dumps(payload))
        return crafted
    payload = torch.load(path, weights_only=True)
    edit(payload)
    torch.save(payload, path.with_name("crafted.pt"))
    return path.with_name("crafted.pt")


def _transformers_image(config: dict | None = None, path: str | None = None):
    def edit(payload):
        payload["backbone"]["image"] = {"kind": "transformers_vision", "path": path, "config": config,
                                        "mean": [0.5] * 3, "std": [0.5] * 3}
        payload["image_weights"] = None
    return edit


POLICY_CRAFTS = {
    "huge-d-model": (lambda p: p["config"].update(d_model=10**7), r"d_model must be an int in \[1, 8192\]"),
    "huge-conv-encoder": (lambda p: p["backbone"]["image"]["config"].update(width=10**6, max_width=10**6),
                          r"image encoder width must be an int in \[1, 512\]"),
    "huge-vit-encoder": (_transformers_image({"model_type": "vit", "hidden_size": 10**6, "image_size": 32,
                                              "patch_size": 8}), r"hidden_size must be an int in \[1, 8192\]"),
    "many-cameras": (lambda p: p.update(cameras=[f"cam{i}" for i in range(10**5)], future_camera="cam0"),
                     r"number of cameras must be an int in \[1, 16\]"),
    "hub-text-encoder": (lambda p: p["backbone"]["text"].update(path="sentence-transformers/all-MiniLM-L6-v2"),
                         r"model 'sentence-transformers/all-MiniLM-L6-v2' is not a local folder; .* offline only"),
    "hub-image-encoder": (_transformers_image(path="google/siglip-base-patch16-224"),
                          r"model 'google/siglip-base-patch16-224' is not a local folder; .* offline only"),
}


@pytest.mark.parametrize("craft", POLICY_CRAFTS)
def test_a_policy_file_cannot_ask_for_absurd_sizes_or_a_download(policy_file, craft):
    edit, problem = POLICY_CRAFTS[craft]
    with pytest.raises(CheckpointError, match=r"crafted(\.pt)?: policy does not load \(\w+Error: " + problem) as error:
        load_policy(_crafted(policy_file, edit))
    assert "\n" not in str(error.value)
    load_policy(policy_file)  # the untouched policy loads


@pytest.mark.parametrize("sizes,problem", [
    ({"n_mmdit": 10**6}, r"n_mmdit must be an int in \[0, 64\]"),
    ({"n_dit": 60, "n_mmdit": 10}, r"n_dit must be an int in \[0, 54\]"),
    ({"horizon": 0}, r"horizon must be an int in \[1, 1024\]"),
    ({"vision_grid": (4, 10**4)}, r"vision_grid must be an int in \[1, 64\]"),
    ({"cond_grid": (10**4, 4)}, r"cond_grid must be an int in \[1, 64\]"),
    ({"mlp_ratio": float("nan")}, r"mlp_ratio must be a finite number"),
    ({"d_model": 8192, "n_heads": 8, "n_mmdit": 8}, r"the trunk would have \d\.\d+e\+10 parameters"),
])
def test_config_sizes_are_capped_before_anything_is_built(sizes, problem):
    with pytest.raises(ValueError, match=problem):
        DustConfig(**sizes)


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_parameter_cap_counts_what_the_trunk_allocates(variant):
    config = DustConfig(variant=variant, d_model=48, n_heads=3, n_mmdit=3, n_dit=2, mlp_ratio=2.5, horizon=5,
                        vision_grid=(2, 3), state_dim=4, action_dim=3, vision_dim=7, cond_dim=20,
                        keypoints=2, aux_state_dim=5, lambda_aux=1.0, aux_state_input=variant == "dust")
    assert config.n_parameters == sum(p.numel() for p in DustModel(config).parameters())


@pytest.mark.parametrize("config,problem", [
    ({"model_type": "llama"}, r"vision model type 'llama' cannot be built from a stored config"),
    ({"model_type": "vit", "hidden_size": 4096, "num_hidden_layers": 64, "num_attention_heads": 32,
      "intermediate_size": 16384}, r"about \d\.\d+e\+10 parameters, more than the cap"),
])
def test_a_stored_vision_config_is_checked_before_a_model_is_built(config, problem):
    with pytest.raises(ValueError, match=problem):
        build_transformers_config(config)
