"""Where does a policy send the arm? Its planned displacement against the expert's, by step in the episode.

For the first ``--episodes`` demonstrations of a dataset, the policy plans a chunk at steps 0, 8, 16
and 24 of the recorded observations; the table gives how far (cm) the sum of the chunk's first 8
position deltas is from the sum of the expert's next 8 (delta control: 2 cm per unit). At step 0 the
arm is at home and the expert heads for the named object, so that row says whether the policy knows
where to go; later rows are easier, since moving on as the arm already moves fits them. Run it on the
training data and on demonstrations of other seeds: a policy that cannot fit its own step-0 rows
cannot use the cameras for that decision. ``--swap-cameras`` gives each row the camera images of the
same step of the next episode (another layout): a policy whose error does not grow ignores the cameras.
``--samples K`` plans K chunks per row and adds how far they scatter around their mean: a policy that
knows where to go samples nearly the same move every time; one that guesses samples the spread of moves.
``--n-action-steps N`` samples with N denoising steps instead of the policy's own.

    .venv/bin/python experiments/first_move_error.py --policy runs/train/T/policy.pt --dataset runs/data/T
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import torch

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.keys import EXPERT_ACTION_KEY, IMAGE_KEY

STEPS, SPAN = (0, 8, 16, 24), 8
CM_PER_UNIT = 100 * MAX_TRANSLATION  # delta control: the pinch point moves this far per unit and step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True)
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--swap-cameras", action="store_true", help="feed the next episode's images")
    parser.add_argument("--samples", type=int, default=1, help="chunks planned per row (> 1: their spread too)")
    parser.add_argument("--n-action-steps", type=int, default=None, help="denoising steps (default: the policy's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.policy).eval()
    if args.n_action_steps is not None:
        policy.set_sampler(replace(policy.config.sampler_settings, n_action_steps=args.n_action_steps))
    dataset = DemoDataset(args.dataset)
    generator = torch.Generator().manual_seed(0)
    errors: dict[int, list[float]] = {step: [] for step in STEPS}
    spreads: dict[int, list[float]] = {step: [] for step in STEPS}
    episodes = dataset.meta["episodes"][:args.episodes]
    for index, episode in enumerate(episodes):
        other = episodes[(index + 1) % len(episodes)]
        steps = [step for step in STEPS if step + SPAN <= min(episode["length"], other["length"])]
        rows = [episode["row_start"] + step for step in steps]
        observed = dataset.with_instructions(dataset.data[rows])
        if args.swap_cameras:
            observed.set(IMAGE_KEY, dataset.data[[other["row_start"] + step for step in steps]].get(IMAGE_KEY))
        moves = torch.stack([policy.plan(observed, generator).get("action_chunk")[:, :SPAN, :3].sum(1)
                             for _ in range(args.samples)])  # [K, rows, 3]
        for i, (step, row) in enumerate(zip(steps, rows)):
            expert = dataset.data[EXPERT_ACTION_KEY][row:row + SPAN, :3].sum(0)
            errors[step].append(CM_PER_UNIT * (moves[0, i] - expert).norm().item())
            spreads[step].append(CM_PER_UNIT * (moves[:, i] - moves[:, i].mean(0)).norm(dim=-1).mean().item())
    spread = args.samples > 1
    print("| step | episodes | planned 8-step displacement to the expert's (cm, mean) | median |"
          + (f" spread of {args.samples} samples around their mean (cm) |" if spread else ""))
    print("|---|---|---|---|" + ("---|" if spread else ""))
    for step, values in errors.items():
        if not values:  # every episode ended before this step
            continue
        values_t = torch.tensor(values)
        extra = f" {torch.tensor(spreads[step]).mean():.1f} |" if spread else ""
        print(f"| {step} | {len(values)} | {values_t.mean():.1f} | {values_t.median():.1f} |{extra}")


if __name__ == "__main__":
    main()
