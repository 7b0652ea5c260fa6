"""experiments/failure_modes.py sorts real peg_insert trajectories: the scripted expert's, cut at each stage.

Why real episodes: the classes read the task's environment-state layout (peg first, then the fixture) and its
heights, which a hand-made trajectory would only restate.
"""

from __future__ import annotations

import importlib.util
import pathlib

import numpy as np
import torch

from dust_rl.envs import DustEnv

_SPEC = importlib.util.spec_from_file_location(
    "failure_modes", pathlib.Path(__file__).parents[1] / "experiments" / "failure_modes.py")
failure_modes = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(failure_modes)


def expert_states(seed: int) -> tuple[torch.Tensor, bool]:
    """The environment state after every step of the expert's peg_insert episode [T, 6], and whether it succeeded."""
    env = DustEnv(task="peg_insert", obs_mode="state")
    env.reset(seed=seed)
    expert = env.make_expert()
    states = []
    for _ in range(env.max_episode_steps):
        observation, _, terminated, truncated, _ = env.step(expert.act())
        states.append(observation["environment_state"])
        if terminated or truncated:
            break
    return torch.as_tensor(np.stack(states)), terminated


def test_peg_insert_stages_of_the_experts_episode_are_sorted_apart():
    states, succeeded = expert_states(seed=0)
    assert succeeded
    classify = failure_modes.peg_insert_mode
    lifted = int(torch.nonzero(states[:, 2] > failure_modes.PEG_LIFTED)[0])
    assert classify(states, success=True) == "success"
    assert classify(states[:2], success=False) == "untouched"  # the arm has not reached the peg yet
    assert classify(states[:lifted + 1], success=False) == "held away from the block"  # just lifted, 17+ cm away
    # the whole episode, had it not counted: the peg ends in the hole, within the block's footprint
    assert classify(states, success=False) == "at the block, not inserted"
    dropped = torch.cat([states[:lifted + 1], states[:1]])  # lifted, then back where it started
    assert classify(dropped, success=False) == "dropped away from the block"
    slid = states[:1].repeat(2, 1)
    slid[1, 0] += 0.02  # pushed 2 cm along the table
    assert classify(slid, success=False) == "not lifted"
