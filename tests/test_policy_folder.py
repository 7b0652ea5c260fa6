"""Policy folders (config.json + model.safetensors, no pickle): everything a policy file holds round-trips, a save
replaces only a policy folder, and every malformed folder is refused with a one-line CheckpointError."""

from __future__ import annotations

import json
import pathlib
import shutil

import pytest
import torch
from crafted import TouchOnUnpickle
from safetensors.torch import load_file, save_file
from test_agents_policy import observation, perturb, tiny_policy

from dust_rl.agents import DustPolicy, SamplerConfig, load_policy, save_policy
from dust_rl.agents.encoders.text_encoder import minilm_path
from dust_rl.agents.factory import POLICY_KIND
from dust_rl.errors import CheckpointError
from dust_rl.storage.checkpoint_files import CONFIG_FILE, MAX_CONFIG_BYTES, WEIGHTS_FILE

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture
def policy(tiny_encoder, minilm) -> DustPolicy:
    """A tiny policy with every stored part moved off its default: weights, stats, bounds, sampler, steps, info."""
    policy = tiny_policy("dust", tiny_encoder, minilm, execute_steps=3)
    perturb(policy)
    with torch.no_grad():
        policy.normalizer.set_stats({"state": {"mean": [1.0] * 5, "std": [2.0] * 5},
                                     "action": {"mean": [0.5, 0, 0], "std": [3.0, 1, 1]}})
        policy.backbone.image.state_dict()["encoder.0.0.weight"].add_(0.5)  # the stored image encoder's own weights
    policy.set_action_bounds(-torch.ones(3), torch.ones(3))
    policy.set_sampler(SamplerConfig("async", 2, 2))
    policy.info = {"env_id": "DustFranka-v0", "tasks": ["pick_place"], "image_size": [32, 32], "steps": 7}
    return policy


def stored(policy: DustPolicy) -> dict:
    """What a save must keep, compared as plain values."""
    return {"config": policy.config, "cameras": policy.cameras, "future_camera": policy.future_camera,
            "execute_steps": policy.execute_steps, "backbone": policy.backbone.reference(), "info": policy.info}


def assert_same_policy(loaded: DustPolicy, policy: DustPolicy) -> None:
    assert stored(loaded) == stored(policy)
    expected = policy.state_dict()  # the rebuilt image encoder included
    assert loaded.state_dict().keys() == expected.keys()
    assert all(torch.equal(value, expected[name]) for name, value in loaded.state_dict().items())
    obs = observation()
    plans = [p.plan(obs, torch.Generator().manual_seed(0)) for p in (policy, loaded)]
    assert torch.equal(plans[0]["action_chunk"], plans[1]["action_chunk"])
    assert torch.equal(plans[0]["future_tokens"], plans[1]["future_tokens"])


def test_a_policy_folder_round_trips_everything_without_pickle(policy, tmp_path):
    folder = save_policy(policy, tmp_path / "policy")
    assert sorted(p.name for p in folder.iterdir()) == [CONFIG_FILE, WEIGHTS_FILE]
    modes = {(folder / name).stat().st_mode & 0o777 for name in (CONFIG_FILE, WEIGHTS_FILE)}
    assert len(modes) == 1  # the weights as readable as the config (the umask's), not safetensors' 0600
    config = json.loads((folder / CONFIG_FILE).read_text())
    assert config["kind"] == POLICY_KIND and config["info"] == policy.info and config["execute_steps"] == 3
    assert "backbone.image.encoder.0.0.weight" in load_file(folder / WEIGHTS_FILE)
    loaded = load_policy(folder)
    assert_same_policy(loaded, policy)
    assert loaded.executor().replan_interval == 3
    # Folder and file hold the same policy: either converts to the other.
    assert_same_policy(load_policy(save_policy(loaded, tmp_path / "again.pt")), policy)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.pt", "policy"]  # no temporary left behind


def test_saving_replaces_a_policy_folder_and_nothing_else(policy, tmp_path, tiny_encoder, minilm):
    folder = save_policy(tiny_policy("action_only", tiny_encoder, minilm), tmp_path / "policy")
    assert_same_policy(load_policy(save_policy(policy, folder)), policy)
    (tmp_path / "empty").mkdir()
    save_policy(policy, tmp_path / "empty")
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "keep.txt").write_text("mine")
    (tmp_path / "file").write_text("mine")
    for target in (notes, tmp_path / "file"):
        with pytest.raises(CheckpointError, match=r"exists and is not a 'dust-rl-policy' checkpoint folder"):
            save_policy(policy, target)
    assert (notes / "keep.txt").read_text() == (tmp_path / "file").read_text() == "mine"
    policy.info = {"not JSON": object()}
    with pytest.raises(TypeError):
        save_policy(policy, tmp_path / "policy")
    assert load_policy(folder).config.variant == "dust"  # the failed save left the old folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "file", "notes", "policy"]


def _edit_config(**entries):
    def edit(folder: pathlib.Path) -> None:
        config = json.loads((folder / CONFIG_FILE).read_text())
        config.update(entries)
        (folder / CONFIG_FILE).write_text(json.dumps({k: v for k, v in config.items() if v is not None}))
    return edit


def _edit_tensors(change):
    def edit(folder: pathlib.Path) -> None:
        tensors = load_file(folder / WEIGHTS_FILE)
        change(tensors)
        save_file(tensors, folder / WEIGHTS_FILE)
    return edit


def _link_out(name: str):
    def edit(folder: pathlib.Path) -> None:
        outside = folder.parent / f"outside-{name}"
        shutil.copy(folder / name, outside)  # the same bytes, only the place differs
        (folder / name).unlink()
        (folder / name).symlink_to(outside)
    return edit


def _text_encoder_tensor(tensors: dict) -> None:
    tensors["backbone.text.model.embeddings.word_embeddings.weight"] = torch.zeros(30522, 384)


def _fill(prefix: str, value: float, dtype: torch.dtype | None = None):
    """Set every floating tensor whose name starts with ``prefix`` to ``value`` (of ``dtype``, default its own)."""
    def change(tensors: dict) -> None:
        for name, tensor in tensors.items():
            if name.startswith(prefix) and tensor.is_floating_point():
                tensors[name] = torch.full_like(tensor, value, dtype=dtype)
    return change


def _with_info(**entries):
    def edit(folder: pathlib.Path) -> None:
        config = json.loads((folder / CONFIG_FILE).read_text())
        (folder / CONFIG_FILE).write_text(json.dumps({**config, "info": {**config["info"], **entries}}))
    return edit


FOLDER_CRAFTS = {
    "config-not-json": (lambda f: (f / CONFIG_FILE).write_text("{'kind': 1"), r"config\.json: not JSON \("),
    "config-a-list": (lambda f: (f / CONFIG_FILE).write_text("[1, 2]"),
                      r"expected a 'dust-rl-policy' checkpoint, found 'list'"),
    "config-too-large": (lambda f: (f / CONFIG_FILE).write_text(" " * (MAX_CONFIG_BYTES + 1)),
                         r"config\.json: \d+ bytes, over the \d+ a checkpoint config may have"),
    "config-without-cameras": (_edit_config(cameras=None), r"policy does not load \(KeyError: 'cameras'\)"),
    "config-other-version": (_edit_config(format_version=2), r"format version 2; this dust-rl reads version 1"),
    "config-unknown-field": (_edit_config(config={"d_model": 32, "colour": "red"}),
                             r"policy does not load \(TypeError: .*'colour'"),
    "config-missing": (lambda f: (f / CONFIG_FILE).unlink(), r"config\.json: missing"),
    "weights-missing": (lambda f: (f / WEIGHTS_FILE).unlink(), r"model\.safetensors: missing"),
    "weights-not-safetensors": (lambda f: (f / WEIGHTS_FILE).write_bytes(b"\x80\x04pickle?"),
                                r"model\.safetensors: corrupt or not safetensors \(SafetensorError: "),
    "tensor-wrong-shape": (_edit_tensors(lambda t: t.update({"model.state_in.weight": torch.zeros(2, 2)})),
                           r"wrong shape \['model\.state_in\.weight \[2, 2\] \(the config makes \[\d+, \d+\]\)'\]"),
    "tensor-extra": (_edit_tensors(lambda t: t.update({"model.extra": torch.zeros(1)})),
                     r"unexpected \['model\.extra'\]"),
    "tensor-of-the-text-encoder": (_edit_tensors(_text_encoder_tensor),
                                   r"unexpected \['backbone\.text\.model\.embeddings\.word_embeddings\.weight'\]"),
    "tensor-missing": (_edit_tensors(lambda t: t.pop("model.state_in.weight")),
                       r"missing \['model\.state_in\.weight'\]"),
    "image-encoder-tensor-missing": (_edit_tensors(lambda t: t.pop("backbone.image.encoder.0.0.weight")),
                                     r"policy does not load \(RuntimeError: .*encoder\.0\.0\.weight"),
    # Content that loads without a complaint and makes every action NaN (or the env check trip over its type).
    "config-nested-too-deep": (lambda f: (f / CONFIG_FILE).write_text("[" * 200_000 + "]" * 200_000),
                               r"config\.json: not JSON \(RecursionError: "),
    "weights-nan": (_edit_tensors(_fill("model.", float("nan"))), r"NaN or infinity in \['model\."),
    "normaliser-nan": (_edit_tensors(_fill("normalizer.state_mean", float("nan"))),
                       r"NaN or infinity in \['normalizer\.state_mean'\]"),
    "normaliser-zero-std": (_edit_tensors(_fill("normalizer.state_std", 0.0)),
                            r"normaliser scales \['normalizer\.state_std'\] hold values <= 0"),
    "weights-int8": (_edit_tensors(_fill("model.", 1, torch.int8)), r"integer values where the model holds floats in "
                                                                    r"\['model\."),
    "image-encoder-weights-inf": (_edit_tensors(_fill("backbone.image.", float("inf"))),
                                  r"NaN or infinity in \['backbone\.image\."),
    "info-image-size-int": (_with_info(image_size=32), r"info\.image_size must be \[height, width\] in pixels, got 32"),
    "info-image-size-text": (_with_info(image_size="32x32"), r"info\.image_size must be .* got '32x32'"),
    "config-links-out": (_link_out(CONFIG_FILE), r"config\.json: links to .*outside-config\.json, outside the"),
    "weights-link-out": (_link_out(WEIGHTS_FILE), r"model\.safetensors: links to .*outside-model\.safetensors"),
}


@pytest.mark.parametrize("craft", FOLDER_CRAFTS)
def test_a_malformed_policy_folder_is_refused_in_one_line(policy, tmp_path, craft):
    edit, problem = FOLDER_CRAFTS[craft]
    folder = save_policy(policy, tmp_path / "policy")
    crafted = shutil.copytree(folder, tmp_path / "crafted")
    edit(crafted)
    with pytest.raises(CheckpointError, match=r"crafted.*" + problem) as error:
        load_policy(crafted)
    assert "\n" not in str(error.value)
    load_policy(folder)  # the untouched folder loads


def test_a_misshapen_tensor_in_a_policy_file_is_refused_in_one_line(policy, tmp_path):
    payload = torch.load(save_policy(policy, tmp_path / "policy.pt"), weights_only=True)
    payload["state_dict"]["model.state_in.weight"] = torch.zeros(2, 2)
    torch.save(payload, tmp_path / "crafted.pt")
    problem = r"crafted\.pt: .*wrong shape \['model\.state_in\.weight \[2, 2\]"
    with pytest.raises(CheckpointError, match=problem) as error:
        load_policy(tmp_path / "crafted.pt")
    assert "\n" not in str(error.value)


def test_a_text_encoder_folder_holding_a_pickle_is_refused_and_never_unpickled(policy, tmp_path):
    """transformers would torch.load a ``pytorch_model.bin`` (a pickle) where ``model.safetensors`` is missing."""
    folder = shutil.copytree(minilm_path(), tmp_path / "encoder", ignore=shutil.ignore_patterns(WEIGHTS_FILE))
    marker = tmp_path / "code-ran"
    torch.save({"weights": TouchOnUnpickle(marker)}, folder / "pytorch_model.bin")
    payload = torch.load(save_policy(policy, tmp_path / "policy.pt"), weights_only=True)
    payload["backbone"]["text"]["path"] = str(folder)
    torch.save(payload, tmp_path / "crafted.pt")
    problem = r"crafted\.pt: policy does not load \(ValueError: model folder .*encoder' does not load .*safetensors"
    with pytest.raises(CheckpointError, match=problem) as error:
        load_policy(tmp_path / "crafted.pt")
    assert "\n" not in str(error.value) and not marker.exists()
