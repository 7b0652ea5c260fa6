"""Demonstration collection: expert fidelity, seeds, resume after a kill, workers, DART noise."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from conftest import DEMO_ENV_KWARGS

from dust_rl.data import DatasetError, DemoDataset, collect_demos
from dust_rl.data.episodes import scan_episodes
from dust_rl.data.policy import ExpertPolicy
from dust_rl.envs import DustEnv
from dust_rl.envs.instruction_space import INSTRUCTION_BYTES, decode_instruction, encode_instruction


def test_episodes_replay_the_scripted_expert(demo_dir):
    dataset = DemoDataset(demo_dir)
    assert dataset.tasks == ["press_button", "open_drawer"]
    assert [(e["task"], e["seed"]) for e in dataset.meta["episodes"]] == [
        ("press_button", 0), ("press_button", 1), ("press_button", 2), ("open_drawer", 0), ("open_drawer", 1),
        ("open_drawer", 2)]
    env = DustEnv(task="press_button", **DEMO_ENV_KWARGS)
    for index in range(3):
        rows = dataset.episode(index)
        obs, info = env.reset(seed=int(rows["seed"][0]))
        expert = env.make_expert()
        assert rows["language_instruction"][0] == info["language_instruction"]
        for t in range(rows.shape[0]):
            assert np.array_equal(rows["observation", "state"][t].numpy(), obs["observation.state"])
            assert np.array_equal(rows["observation", "image", "front"][t].permute(1, 2, 0).numpy(),
                                  obs["observation.image.front"])
            action = expert.act()
            assert np.allclose(rows["expert_action"][t].numpy(), np.clip(action, -1, 1))
            obs, reward, terminated, truncated, info = env.step(action)
            assert rows["next", "reward"][t].item() == reward
            assert bool(rows["next", "done"][t]) == (terminated or truncated)
        assert terminated and info["is_success"] and rows["next", "success"][-1]
    env.close()
    assert torch.equal(dataset.data["action"], dataset.data["expert_action"])  # no noise: executed = label
    for episode in dataset.meta["episodes"]:
        rows = dataset.episode(episode["index"])
        assert torch.equal(rows["frame_index"], torch.arange(episode["length"]))
        assert (rows["seed"] == episode["seed"]).all() and (rows["episode"] == episode["index"]).all()
    stats = dataset.meta["stats"]["observation.state"]
    assert np.allclose(stats["mean"], dataset.data["observation", "state"].double().mean(0).numpy())


def test_rerun_is_a_no_op_and_other_settings_are_refused(demo_dir):
    before = json.loads((demo_dir / "meta.json").read_text())
    collect_demos(demo_dir, tasks=["press_button", "open_drawer"], episodes=3, env_kwargs=DEMO_ENV_KWARGS,
                  progress=False)
    assert json.loads((demo_dir / "meta.json").read_text()) == before
    with pytest.raises(DatasetError, match="image_size"):
        collect_demos(demo_dir, tasks=["press_button"], episodes=3, env_kwargs={"image_size": 48}, progress=False)
    with pytest.raises(DatasetError, match="noise_std"):
        collect_demos(demo_dir, tasks=["press_button"], episodes=3, env_kwargs=DEMO_ENV_KWARGS, noise_std=0.1,
                      progress=False)


def _collect_command(out, episodes: int, workers: int) -> list[str]:
    return [sys.executable, "-m", "dust_rl.cli", "collect", "--task", "press_button", "--episodes", str(episodes),
            "--image-size", "32", "--out", str(out), "--workers", str(workers)]


def test_killed_collection_resumes_with_two_workers_without_duplicates(tmp_path, demo_dir):
    out = tmp_path / "ds"
    proc = subprocess.Popen(_collect_command(out, 40, 1), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while len(list((out / "episodes" / "press_button").glob("seed-*"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = scan_episodes(out)["press_button"]
    assert 2 <= len(finished) < 40, "the kill must land mid-collection"
    assert '"data": null' in (out / "meta.json").read_text()
    with pytest.raises(DatasetError, match="not finished"):
        DemoDataset(out)
    # A writer killed mid-episode leaves a half-written staging folder behind.
    (out / ".staging" / "dead").mkdir(parents=True, exist_ok=True)
    (out / ".staging" / "dead" / "partial.memmap").write_bytes(b"\0" * 10)

    subprocess.run(_collect_command(out, 40, 2), check=True, capture_output=True)  # the same command, 2 workers
    resumed = DemoDataset(out)
    seeds = [e["seed"] for e in resumed.meta["episodes"]]
    assert seeds == sorted(set(seeds)) and len(seeds) == 40 and not (out / ".staging").exists()
    # Each episode keeps its own instruction, also those a worker process ran after its first.
    env = DustEnv(task="press_button", obs_mode="state")
    truth = [env.reset(seed=seed)[1]["language_instruction"] for seed in seeds]
    env.close()
    stored = [resumed.instructions[e["instruction_index"]] for e in resumed.meta["episodes"]]
    assert stored == truth and len(set(truth)) > 2
    reference = DemoDataset(demo_dir)  # collected in one go, in-process
    assert seeds[:3] == [e["seed"] for e in reference.meta["episodes"][:3]]
    rows = reference.meta["episodes"][2]["row_start"] + reference.meta["episodes"][2]["length"]
    assert torch.equal(resumed.data["action"][:rows], reference.data["action"][:rows])
    assert torch.equal(resumed.data["observation", "image", "wrist"][:rows],
                       reference.data["observation", "image", "wrist"][:rows])


def test_dart_noise_perturbs_execution_not_labels(tmp_path):
    policy = ExpertPolicy(noise_std=0.5)
    expert = torch.zeros(2, 7)
    seed, step = torch.tensor([[3], [3]]), torch.tensor([[5], [6]])
    assert torch.equal(policy(expert, seed, step), policy(expert, seed, step))
    assert not torch.equal(policy(expert, seed, step)[0], policy(expert, seed, step)[1])

    meta = collect_demos(tmp_path / "noisy", tasks=["press_button"], episodes=1, env_kwargs=DEMO_ENV_KWARGS,
                         noise_std=0.2, progress=False)
    data = DemoDataset(tmp_path / "noisy").data
    assert meta["noise_std"] == 0.2
    gap = (data["action"] - data["expert_action"]).abs()
    assert gap.max() > 0.05 and gap.max() <= 1.0
    seed = meta["episodes"][0]["seed"]
    env = DustEnv(task="press_button", **DEMO_ENV_KWARGS)
    env.reset(seed=seed)
    for t in range(3):  # the stored executed actions replay the episode
        obs, *_ = env.step(data["action"][t].numpy())
        assert np.array_equal(obs["observation.state"], data["observation", "state"][t + 1].numpy())
    env.close()


def test_instructions_travel_as_bytes():
    for text in ("put the red cube on the plate", "", "stelle den grünen Würfel ab"):
        encoded = encode_instruction(text)
        assert encoded.shape == (INSTRUCTION_BYTES,) and encoded.dtype == np.uint8
        assert decode_instruction(torch.as_tensor(encoded)) == text
    with pytest.raises(ValueError, match="UTF-8 bytes"):
        encode_instruction("ü" * INSTRUCTION_BYTES)
