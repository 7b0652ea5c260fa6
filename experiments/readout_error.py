"""How far is a policy's object-state read-out from the truth, by time in the episode?

Prints :func:`dust_rl.train.readout.error.readout_error_table` (why: that module's doc) for a trained policy.

    .venv/bin/python experiments/readout_error.py --policy runs/train/T/policy.pt --dataset runs/data/T_val
"""

from __future__ import annotations

import argparse

import torch

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.train.readout.error import readout_error_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="policy.pt trained with --policy.lambda-aux")
    parser.add_argument("--dataset", required=True, help="demonstrations from other seeds than the training data")
    parser.add_argument("--columns", type=int, default=3, help="object-state columns per object (press_button: 4)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.policy)
    print(readout_error_table(policy, DemoDataset(args.dataset), EnvStateNorm.of_policy(policy), args.columns))


if __name__ == "__main__":
    main()
