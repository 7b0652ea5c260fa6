"""Collecting a trained policy's rollouts: the evaluated episodes, the expert's label beside them, bad input."""

from __future__ import annotations

import pytest
import torch
from test_evaluate import tiny_policy_file

from dust_rl.agents import load_policy
from dust_rl.data import DatasetError, collect_demos
from dust_rl.data.collect import MAX_SEEDS_PER_EPISODE, SuccessesOutOfReachError
from dust_rl.data.episodes import load_episode_rows, scan_episodes
from dust_rl.data.seeding import SeedSchedule
from dust_rl.errors import CheckpointError, ConfigError
from dust_rl.evaluate.closed_loop import make_eval_env

pytestmark = pytest.mark.usefixtures("one_thread")

ENV_KWARGS = {"image_size": 32, "max_episode_steps": 5}  # tiny_policy_file's cameras; 5-step episodes


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory, minilm):
    return tiny_policy_file(tmp_path_factory.mktemp("policy") / "policy.pt", minilm)


@pytest.fixture(scope="module")
def rollouts(policy_path, tmp_path_factory):
    """An untrained policy never succeeds: the collection keeps every failure until it gives up."""
    root = tmp_path_factory.mktemp("rollouts")
    with pytest.raises(SuccessesOutOfReachError, match="press_button policy succeeded in only 0 of .* the policy"):
        collect_demos(root, tasks=["press_button"], episodes=1, env_kwargs=ENV_KWARGS, keep_failed=True,
                      policy=policy_path, progress=False)
    return root


def test_stored_rollouts_are_the_policys_evaluated_episodes(rollouts, policy_path):
    records = scan_episodes(rollouts)["press_button"]
    assert sorted(records) == list(range(MAX_SEEDS_PER_EPISODE["policy"] + 10))
    assert all(record.kept and not record.success and record.length == 5 for record in records.values())
    rows = load_episode_rows(rollouts, records[3])
    env = make_eval_env("DustFranka-v0", {**ENV_KWARGS, "task": "press_button"}, SeedSchedule(3))
    evaluated = env.rollout(10, load_policy(policy_path).executor(seeded=True), break_when_any_done=True)
    env.close()
    assert torch.equal(rows["action"], evaluated["action"])  # the same episode, bit for bit
    assert torch.equal(rows["observation", "state"], evaluated["observation", "state"])
    assert not torch.equal(rows["action"], rows["expert_action"])  # the expert's label rides along


def test_a_resumed_collection_refuses_another_policy(rollouts, tmp_path, minilm):
    other = tiny_policy_file(tmp_path / "other.pt", minilm,
                             info={"env_id": "DustFranka-v0", "tasks": [], "image_size": [32, 32]})
    with pytest.raises(DatasetError, match="policy"):
        collect_demos(rollouts, tasks=["press_button"], episodes=1, env_kwargs=ENV_KWARGS, keep_failed=True,
                      policy=other, progress=False)


def test_bad_policy_input_fails_before_anything_is_written(policy_path, tmp_path, minilm):
    with pytest.raises(ConfigError, match="noise_std"):
        collect_demos(tmp_path / "noisy", tasks=["press_button"], episodes=1, env_kwargs=ENV_KWARGS,
                      noise_std=0.1, policy=policy_path, progress=False)
    other_actions = tiny_policy_file(tmp_path / "three.pt", minilm, action_dim=3)
    for path in (other_actions, tmp_path / "missing.pt"):
        with pytest.raises(CheckpointError):
            collect_demos(tmp_path / "bad", tasks=["press_button"], episodes=1, env_kwargs=ENV_KWARGS,
                          policy=path, progress=False)
    assert not (tmp_path / "noisy").exists() and not (tmp_path / "bad").exists()
