"""How much a policy's success depends on its sampling noise: the headroom of noise-space steering and selection.

Why: steering (``dust-rl finetune --method steer``) and best-of-K selection (``wm_select``) can only choose among
what the base policy samples. If a layout fails whatever the noise, no choice of noise helps; if it succeeds under
some draws, a perfect chooser would win it. So each layout is evaluated K times with K different noise streams
(the evaluation's per-episode noise seed shifted by a large offset), and the script prints the mean success over
the draws against the share of layouts won by at least one draw: the best any noise chooser could reach.

    .venv/bin/python scripts/noise_headroom.py --policy runs/train/T/policy.pt [--draws 4] [--seed 5000] \
        [--episodes 50]
"""

from __future__ import annotations

import argparse

import torch
from in_process_eval import add_eval_arguments, prepare_in_process

from dust_rl.agents import execution
from dust_rl.evaluate import evaluate_task, wilson_interval

NOISE_OFFSET = 1_000_003  # added to the episode seed per draw: far from every seed schedule


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)
    parser.add_argument("--draws", type=int, default=4, help="noise streams per layout (K)")
    args = parser.parse_args()
    if args.draws < 1:
        parser.error("--draws needs K >= 1")
    policy, setup, config = prepare_in_process(args)
    unshifted = execution.episode_generator
    wins = torch.zeros(args.draws, len(setup.tasks), args.episodes, dtype=torch.bool)
    for draw in range(args.draws):
        execution.episode_generator = lambda seed, draw=draw: unshifted(int(seed) + draw * NOISE_OFFSET)
        for t, task in enumerate(setup.tasks):
            episodes, _, _, _ = evaluate_task(setup, task, policy, config)
            wins[draw, t] = torch.tensor([e.success for e in episodes])
        print(f"draw {draw}: {int(wins[draw].sum())}/{wins[draw].numel()}")
    execution.episode_generator = unshifted
    mean, best = int(wins.sum()), int(wins.any(0).sum())
    n = wins[0].numel()
    low, high = wilson_interval(best, n)
    print(f"{args.policy}, seeds {args.seed}..{args.seed + args.episodes - 1}, {args.draws} noise draws per layout: "
          f"mean success {mean / (args.draws * n):.0%}; layouts won by at least one draw {best}/{n} ({best / n:.0%}, "
          f"95% CI {low:.0%}-{high:.0%}); won by every draw {int(wins.all(0).sum())}/{n}")


if __name__ == "__main__":
    main()
