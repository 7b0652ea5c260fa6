"""ExpertActionWrapper: every observation an action follows carries the expert's label, the terminal one none."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from conftest import DEMO_ENV_KWARGS

from dust_rl.envs.expert_wrapper import ExpertActionWrapper, scripted_expert
from dust_rl.keys import EXPERT_ACTION_KEY


class CountingExpert:
    """The scripted expert, counting how often it is asked."""

    def __init__(self, env: gym.Env, seed: int | None) -> None:
        self.expert, self.calls = scripted_expert(env, seed), 0

    def act(self) -> np.ndarray:
        self.calls += 1
        return self.expert.act()


def test_labels_follow_the_expert_and_the_terminal_observation_asks_nothing():
    experts: list[CountingExpert] = []

    def make_expert(env: gym.Env, seed: int | None) -> CountingExpert:
        experts.append(CountingExpert(env, seed))
        return experts[-1]

    env = ExpertActionWrapper(gym.make("DustFranka-v0", task="press_button", **DEMO_ENV_KWARGS), make_expert)
    obs, _ = env.reset(seed=0)
    reference = env.unwrapped.make_expert()  # the same scripted expert, asked once per step alongside
    steps, done = 0, False
    while not done:
        assert np.array_equal(obs[EXPERT_ACTION_KEY], np.clip(reference.act(), -1, 1).astype(np.float32))
        obs, _, terminated, truncated, _ = env.step(obs[EXPERT_ACTION_KEY])
        steps, done = steps + 1, terminated or truncated
    assert experts[-1].calls == steps  # one label per action taken, none for the terminal observation
    assert not np.any(obs[EXPERT_ACTION_KEY]) and env.observation_space.contains(obs)
    env.close()
