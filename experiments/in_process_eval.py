"""The shared part of the diagnostics that evaluate a policy in this process with hooks attached.

Why in this process: the hooks (forward hooks on the policy, a swapped ``plan_features`` or noise generator) must
reach the policy that acts, so the evaluation runs one env, here (``workers=1``, the local collector).
"""

from __future__ import annotations

import argparse
import pathlib
from collections.abc import Sequence

import torch

from dust_rl.agents import DustPolicy, execution
from dust_rl.evaluate.closed_loop import EvalConfig, EvalSetup, prepare, summary_row
from dust_rl.evaluate.records import Episode
from dust_rl.runtime.settings import RuntimeSettings

NOISE_OFFSET = 1_000_003  # added to the episode seed per further draw: far from every seed schedule


class PlanHook:
    """Inside a ``with`` block, the acting policy plans through :meth:`_plan_features` and every episode's noise
    generator comes from :meth:`_episode_generator` (both pass through here; subclasses watch or change them);
    leaving the block restores both."""

    def __init__(self, policy: DustPolicy) -> None:
        self.policy = policy

    def __enter__(self):
        self.unshifted, self.plan_features = execution.episode_generator, self.policy.plan_features
        execution.episode_generator = self._episode_generator
        self.policy.plan_features = self._plan_features
        return self

    def __exit__(self, *exc: object) -> None:
        execution.episode_generator = self.unshifted
        del self.policy.plan_features  # the class's method again

    def _episode_generator(self, seed: int) -> torch.Generator:
        return self.unshifted(seed)

    def _plan_features(self, *args, **kwargs):
        return self.plan_features(*args, **kwargs)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """``--policy``, ``--seed``, ``--episodes`` and ``--threads``."""
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)


def prepare_in_process(args: argparse.Namespace) -> tuple[DustPolicy, EvalSetup, EvalConfig]:
    """The policy (to attach hooks to), its evaluation setup and config, one env in this process, no videos."""
    config = EvalConfig(policy=args.policy, seed=args.seed, episodes=args.episodes, workers=1, videos=0,
                        runtime=RuntimeSettings(threads=args.threads, device="cpu", progress=False))
    torch.set_num_threads(args.threads)
    policy, setup = prepare(config)
    return policy, setup, config


def success_line(task: str, episodes: Sequence[Episode]) -> str:
    """``k/n (95% CI a%-b%)``."""
    row = summary_row(task, episodes)
    return f"{row['successes']}/{row['episodes']} (95% CI {row['ci95_low']:.0%}-{row['ci95_high']:.0%})"
