"""An env pickles as its constructor arguments and RNG (vector envs and worker processes ship no simulator); a
deep copy keeps the whole state."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import numpy as np
from conftest import assert_same_observations, seeded_rollout

import dust_rl  # noqa: F401  (registers the ids)

KWARGS = {"task": "press_button", "image_size": 32, "reward_type": "dense"}


def test_a_pickled_env_is_small_and_rebuilds_as_built():
    env = gym.make("DustFranka-v0", **KWARGS)
    env.reset(seed=3)
    env.step(env.action_space.sample())
    blob = pickle.dumps(env)
    assert len(blob) < 1_000_000
    clone = pickle.loads(blob)
    assert_same_observations([clone.reset()[0]], [env.reset()[0]])  # unseeded: the RNG goes on where it was
    fresh = gym.make("DustFranka-v0", **KWARGS)
    for seed in (0, 5):
        assert_same_observations(*(seeded_rollout(e, seed, steps=5)[0] for e in (clone, fresh)))
    for e in (env, clone, fresh):
        e.close()


def test_a_deep_copy_goes_on_from_the_same_state():
    env = gym.make("DustFranka-v0", **KWARGS)
    env.reset(seed=4)
    action = np.full(7, 0.5, np.float32)
    env.step(action)  # renders: the copy makes a renderer of its own
    twin = copy.deepcopy(env)
    for _ in range(3):
        (obs, reward, *_), (twin_obs, twin_reward, *_) = env.step(action), twin.step(action)
        assert_same_observations([obs], [twin_obs])
        assert reward == twin_reward
    env.close()
    twin.close()
