"""The SB3 from-scratch reference benchmark: real SB3 on the real state-mode env, a few hundred steps."""

from __future__ import annotations

import json

import pytest

from dust_rl.bench.sb3_scratch import train_from_scratch
from dust_rl.data.seeding import HELDOUT_SEED
from dust_rl.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_thread")


def test_sac_from_scratch_curve_heldout_and_determinism(tmp_path):
    run = {"task": "press_button", "algorithm": "sac", "steps": 300, "eval_every": 150, "curve_episodes": 1,
           "episodes": 2, "progress": False}
    results = train_from_scratch(out=tmp_path / "a", **run)
    assert [point["env_steps"] for point in results["curve"]] == [150, 300]
    assert all(point["episodes"] == 1 for point in results["curve"])
    assert (tmp_path / "a" / "learning_curve.png").stat().st_size > 0
    assert json.loads((tmp_path / "a" / "results.json").read_text()) == json.loads(json.dumps(results))
    heldout = results["heldout"]
    assert [episode["seed"] for episode in heldout["per_episode"]] == [HELDOUT_SEED, HELDOUT_SEED + 1]
    assert heldout["episodes"] == 2 and results["env_steps"] == 300
    # The same seed trains the same agent: the same held-out episodes, digest for digest.
    again = train_from_scratch(out=tmp_path / "b", **run)
    assert again["heldout"]["per_episode"] == heldout["per_episode"]


def test_ppo_trains_and_bad_input_is_refused(tmp_path):
    results = train_from_scratch("press_button", "ppo", 64, tmp_path, episodes=1, progress=False)
    assert results["env_steps"] == 64 and results["curve"] == [] and results["heldout"]["episodes"] == 1
    with pytest.raises(ConfigError, match="unknown algorithm 'dqn'"):
        train_from_scratch("press_button", "dqn", 64, tmp_path)
    with pytest.raises(ConfigError, match="must be >= 1"):
        train_from_scratch("press_button", "sac", 0, tmp_path)
    with pytest.raises(ConfigError, match="no_such_task"):
        train_from_scratch("no_such_task", "sac", 64, tmp_path)
