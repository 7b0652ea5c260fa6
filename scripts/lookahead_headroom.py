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
import pathlib

import torch

from dust_rl.agents import load_policy, unwrap
from dust_rl.env_factory import make_env
from dust_rl.evaluate import wilson_interval
from dust_rl.search_expert import SearchExpertFactory
from dust_rl.search_settings import SearchSettings


def run(policy: pathlib.Path, settings: SearchSettings, seeds: range) -> tuple[list[bool], int, int]:
    """Success of the search expert's episode on each seed; env steps executed and tried by the search."""
    trained = unwrap(load_policy(policy)).info
    env = make_env(trained["env_id"], {**trained.get("env_kwargs", {}), "task": trained["tasks"][0]})
    factory, wins, executed, simulated = SearchExpertFactory(policy, settings), [], 0, 0
    for seed in seeds:
        env.reset(seed=seed)
        expert = factory(env.unwrapped, seed)
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, info = env.step(expert.act())
            executed += 1
        wins.append(bool(info["is_success"]))
        simulated += expert.simulated
    env.close()
    return wins, executed, simulated


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
        wins, executed, simulated = run(args.policy, SearchSettings(k, args.lookahead, args.noise_scale), seeds)
        low, high = wilson_interval(sum(wins), len(wins))
        print(f"K={k} lookahead={args.lookahead} noise x{args.noise_scale:g}: {sum(wins)}/{len(wins)} "
              f"({100 * sum(wins) / len(wins):.0f}%, CI {100 * low:.0f}-{100 * high:.0f}%); env steps executed "
              f"{executed}, tried by the search {simulated}; won: "
              f"{[seed for seed, won in zip(seeds, wins) if won]}", flush=True)


if __name__ == "__main__":
    main()
