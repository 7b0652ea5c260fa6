"""What a chunk chooser that sees each candidate's outcome could win: the headroom of selection and steering.

Why: best-of-K selection (``wm_select``) and noise steering pick among chunks the base policy samples. Which of
K chunks to pick is what a learnt chunk value would answer; here the simulator answers it (the search expert of
:mod:`dust_rl.search_expert`: K chunks per plan, each tried from a snapshot for ``--lookahead`` chunks, the one
with the most progress executed). If even this oracle cannot lift the base policy by the issue's 20 points, no
learnt chooser of that kind will. ``--candidates 1`` is the plain evaluation, episode for episode.

    .venv/bin/python scripts/lookahead_headroom.py --policy runs/train/T/policy.pt --candidates 1 4 8 \
        [--lookahead 3] [--noise-scale 2] [--seed 5000] [--episodes 50]
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import torch

from dust_rl.env_factory import make_env
from dust_rl.evaluate import wilson_interval
from dust_rl.search_expert import Choice, SearchExpertFactory
from dust_rl.search_settings import SearchSettings


@dataclasses.dataclass
class SearchRun:
    """The search expert's episodes: success per seed, env steps executed and tried, and with ``record`` each
    plan's :class:`~dust_rl.search_expert.Choice` and the episode index of each."""

    wins: list[bool]
    executed: int = 0
    simulated: int = 0
    choices: list[Choice] = dataclasses.field(default_factory=list)
    episode_of_choice: list[int] = dataclasses.field(default_factory=list)


def run(policy: pathlib.Path, settings: SearchSettings, seeds: range, record: bool = False) -> SearchRun:
    """The search expert's episode on each seed."""
    factory, result = SearchExpertFactory(policy, settings), SearchRun([])
    trained = factory.policy.info
    env = make_env(trained["env_id"], {**trained.get("env_kwargs", {}), "task": trained["tasks"][0]})
    for index, seed in enumerate(seeds):
        env.reset(seed=seed)
        expert = factory(env.unwrapped, seed)
        expert.choices = [] if record else None
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, info = env.step(expert.act())
            result.executed += 1
        result.wins.append(bool(info["is_success"]))
        result.simulated += expert.simulated
        if record:
            result.choices += expert.choices
            result.episode_of_choice += [index] * len(expert.choices)
    env.close()
    return result


def describe(settings: SearchSettings, seeds: range, result: SearchRun) -> str:
    """One line: success with its interval, env steps, the seeds won."""
    wins = result.wins
    low, high = wilson_interval(sum(wins), len(wins))
    return (f"K={settings.candidates} lookahead={settings.lookahead} noise x{settings.noise_scale:g}: {sum(wins)}/"
            f"{len(wins)} ({100 * sum(wins) / len(wins):.0f}%, CI {100 * low:.0f}-{100 * high:.0f}%); env steps "
            f"executed {result.executed}, tried by the search {result.simulated}; won: "
            f"{[seed for seed, won in zip(seeds, wins) if won]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--candidates", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--lookahead", type=int, default=1)
    parser.add_argument("--noise-scale", type=float, default=1.0,
                        help="the initial noise in multiples of the trained one (a sampling temperature)")
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = range(args.seed, args.seed + args.episodes)
    for k in args.candidates:
        settings = SearchSettings(k, args.lookahead, args.noise_scale)
        print(describe(settings, seeds, run(args.policy, settings, seeds)), flush=True)


if __name__ == "__main__":
    main()
