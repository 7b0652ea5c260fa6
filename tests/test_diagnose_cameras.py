"""`dust-rl diagnose cameras`: the same episodes with each camera's tokens replaced by the training mean."""

from __future__ import annotations

import json
import pathlib

import pytest
import torch
from tensordict import TensorDict
from test_evaluate import tiny_policy_file

from dust_rl.agents import load_policy, save_policy
from dust_rl.cli import main
from dust_rl.evaluate.records import Episode

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_mean_camera_reads_as_the_training_mean_token(tmp_path, minilm):
    policy = load_policy(tiny_policy_file(tmp_path / "policy.pt", minilm))
    with torch.no_grad():
        policy.normalizer.vision_mean.uniform_(-1.0, 1.0)  # a mean no frame's tokens happen to have
    frames = {("observation", "image", cam): torch.randint(0, 256, (2, 3, 32, 32), dtype=torch.uint8)
              for cam in policy.cameras}
    td = TensorDict({**frames, ("observation", "state"): torch.zeros(2, 17),
                     "language_instruction": ["press the red button"] * 2}, batch_size=[2])
    full = policy.observation_features(td).get("image_tokens")
    policy.set_mean_cameras(["wrist"])
    ablated = policy.observation_features(td).get("image_tokens")
    assert torch.equal(ablated[:, 0], full[:, 0])  # the front camera as it was
    assert torch.equal(ablated[:, 1], policy.normalizer.vision_mean.expand_as(ablated[:, 1]))
    with pytest.raises(ValueError, match=r"no camera \['top'\]"):
        policy.set_mean_cameras(["top"])


def test_every_arm_runs_the_same_episodes_and_is_compared_with_all_cameras(tmp_path, minilm, capsys):
    untrained = load_policy(tiny_policy_file(tmp_path / "untrained.pt", minilm))
    with torch.no_grad():  # weights off their zero-gated start, so what the cameras show moves the actions
        for parameter in untrained.trainable_modules().parameters():
            parameter.add_(0.3 * torch.randn(parameter.shape, generator=torch.Generator().manual_seed(0)))
    policy = save_policy(untrained, tmp_path / "policy.pt")
    out = tmp_path / "cameras"
    main(["diagnose", "cameras", "--policy", str(policy), "--out", str(out), "--episodes", "2", "--max-steps", "6",
          "--workers", "1", "--runtime.no-progress"])
    report = json.loads((out / "report.json").read_text())
    assert [row["arm"] for row in report["rows"]] == ["all cameras", "front as its mean", "wrist as its mean"]
    assert "vs_all" not in report["rows"][0] and all("vs_all" in row for row in report["rows"][1:])
    episodes = {row["arm"]: [Episode.from_json(e) for e in json.loads(pathlib.Path(row["report"]).read_text())[
        "tasks"][0]["per_episode"]] for row in report["rows"]}
    seeds = {arm: [e.seed for e in rows] for arm, rows in episodes.items()}
    assert len(set(map(tuple, seeds.values()))) == 1  # the same seeds
    full = [e.digest for e in episodes["all cameras"]]
    assert all([e.digest for e in episodes[arm]] != full for arm in episodes if arm != "all cameras")  # other acts
    assert "| wrist as its mean |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["diagnose", "cameras", "--policy", str(tmp_path / "missing.pt"), "--out", str(out)])
