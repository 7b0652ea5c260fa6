"""The search expert: simulator snapshots, the plain policy at one candidate, the best candidate executed, and
its rollouts collected as a dataset."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_evaluate import tiny_policy_file

from dust_rl.agents import load_policy, seeded_executor, unwrap
from dust_rl.data import collect_demos
from dust_rl.data.collect import SuccessesOutOfReachError
from dust_rl.data.episodes import load_episode_rows, scan_episodes
from dust_rl.data.seeding import SeedSchedule
from dust_rl.env_factory import make_env
from dust_rl.errors import ConfigError
from dust_rl.evaluate import make_eval_env
from dust_rl.finetune import FinetuneConfig
from dust_rl.search_expert import SearchExpertFactory
from dust_rl.search_settings import SearchSettings

pytestmark = pytest.mark.usefixtures("one_thread")

ENV_KWARGS = {"image_size": 32, "max_episode_steps": 12}  # tiny_policy_file's cameras
TASK = "press_button"


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory, minilm):
    return tiny_policy_file(tmp_path_factory.mktemp("policy") / "policy.pt", minilm)


def sim_env() -> gym.Env:
    return make_env("DustFranka-v0", {**ENV_KWARGS, "task": TASK, "reward_type": "dense"})


def test_restore_replays_the_steps_after_a_snapshot_bit_for_bit():
    env = sim_env()
    env.reset(seed=3)
    actions = np.random.default_rng(0).uniform(-1, 1, (6, 7)).astype(np.float32)
    env.step(actions[0])
    snapshot = env.unwrapped.snapshot()
    first = [env.step(a) for a in actions[1:]]
    env.unwrapped.restore(snapshot)
    again = [env.step(a) for a in actions[1:]]
    for (obs_a, reward_a, *flags_a), (obs_b, reward_b, *flags_b) in zip(first, again, strict=True):
        assert reward_a == reward_b and flags_a[:2] == flags_b[:2]
        for key, value in obs_a.items():
            assert np.array_equal(value, obs_b[key]) if isinstance(value, np.ndarray) else value == obs_b[key]
    assert not np.array_equal(first[0][0]["observation.state"], first[-1][0]["observation.state"])  # it moved
    env.close()


def search_episode(policy_path, settings: SearchSettings, seed: int) -> np.ndarray:
    env = sim_env()
    env.reset(seed=seed)
    expert, actions, done = SearchExpertFactory(policy_path, settings)(env.unwrapped, seed), [], False
    while not done:
        actions.append(expert.act())
        _, _, terminated, truncated, _ = env.step(actions[-1])
        done = terminated or truncated
    env.close()
    return np.stack(actions)


def test_one_candidate_is_the_evaluated_policy(policy_path):
    actions = search_episode(policy_path, SearchSettings(candidates=1), seed=4)
    env = make_eval_env("DustFranka-v0", {**ENV_KWARGS, "task": TASK}, SeedSchedule(4))
    evaluated = env.rollout(50, seeded_executor(unwrap(load_policy(policy_path))), break_when_any_done=True)
    env.close()
    assert np.array_equal(actions, evaluated["action"].numpy())


def test_the_best_scoring_candidate_is_executed_and_the_simulator_is_left_as_it_was(policy_path):
    settings = SearchSettings(candidates=3, lookahead=2)
    env = sim_env()
    env.reset(seed=5)
    before = env.unwrapped.snapshot()
    judge = SearchExpertFactory(policy_path, settings)(env.unwrapped, 5)
    candidates = [judge.plan()[0] for _ in range(settings.candidates)]
    scores = []
    for chunk in candidates:
        scores.append(judge.score(chunk))
        env.unwrapped.restore(before)
    expert = SearchExpertFactory(policy_path, settings)(env.unwrapped, 5)  # the same noise stream
    expert.choices = []
    chosen = expert.choose()
    assert torch.equal(chosen, candidates[int(np.argmax(scores))])
    choice, = expert.choices  # each candidate with its predicted future and score, for fitting a ranker
    assert torch.equal(choice.scores, torch.tensor(scores)) and torch.equal(choice.chunks, torch.stack(candidates))
    assert choice.futures.shape[0] == settings.candidates
    assert len({round(s, 12) for s in scores}) > 1  # the candidates differ, so the choice is a real one
    assert np.array_equal(env.unwrapped.data.qpos, before.data.qpos) and env.unwrapped._elapsed == before.elapsed
    env.close()


def test_search_rollouts_are_a_dataset_of_the_searchs_actions(policy_path, tmp_path):
    settings = SearchSettings(candidates=2, lookahead=1)
    with pytest.raises(SuccessesOutOfReachError, match="succeeded in only 0 of"):  # an untrained policy never succeeds
        collect_demos(tmp_path, tasks=[TASK], episodes=1, env_kwargs=ENV_KWARGS, keep_failed=True,
                      policy=policy_path, search=settings, progress=False)
    records = scan_episodes(tmp_path)[TASK]
    rows = load_episode_rows(tmp_path, records[0])
    assert torch.equal(rows["action"], rows["expert_action"])  # the search acted; its actions are the labels
    searched = np.clip(search_episode(policy_path, settings, seed=0), -1.0, 1.0)  # as the env executes them
    np.testing.assert_array_equal(rows["action"].numpy(), searched)
    meta_policy = json.loads((tmp_path / "meta.json").read_text())["policy"]
    assert meta_policy["search"] == {"candidates": 2, "lookahead": 1, "noise_scale": 1.0}


def test_bad_search_settings_are_refused(policy_path, tmp_path):
    for bad in ({"candidates": 0}, {"lookahead": 0}, {"noise_scale": float("nan")}, {"noise_scale": 0.0}):
        with pytest.raises(ConfigError, match="search"):
            SearchSettings(**bad)
    with pytest.raises(ConfigError, match="pass the policy"):
        collect_demos(tmp_path / "no_policy", tasks=[TASK], episodes=1, env_kwargs=ENV_KWARGS,
                      search=SearchSettings(candidates=2), progress=False)
    with pytest.raises(ConfigError, match="self_imitation"):
        FinetuneConfig(policy=policy_path, method="steer", search=SearchSettings(candidates=2))
    assert not (tmp_path / "no_policy").exists()
