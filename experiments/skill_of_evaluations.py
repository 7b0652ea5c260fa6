"""The world model's skill (``wm/skill``) of every periodic evaluation of a training run, computed anew.

Runs trained before the skill windows were put in the trunk's units at every evaluation logged a skill measured on
condition tokens of the untrained condition layers (-0.68 where the weights' own was +0.67). Each evaluation's
policy file is in ``eval/step-<N>/``; this scores it on the windows training scores (``SKILL_WINDOWS`` of the
training dataset, seed 0) and prints one line per evaluation.

    .venv/bin/python experiments/skill_of_evaluations.py --run runs/study/curve_all_dust \
        --dataset runs/data/franka_all_100
"""

from __future__ import annotations

import argparse
import pathlib

import torch

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset
from dust_rl.data.features import FeatureCache
from dust_rl.diagnose.world_model import vision_skill, windows_of
from dust_rl.train.imitation import SKILL_WINDOWS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=pathlib.Path, required=True)
    parser.add_argument("--dataset", type=pathlib.Path, required=True, help="the run's training dataset")
    parser.add_argument("--seed", type=int, default=0, help="the run's --seed")
    parser.add_argument("--batch-size", type=int, default=64, help="the run's --optim.batch-size")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dataset = DemoDataset(args.dataset)
    print("| step | wm/skill |\n|---|---|")
    for folder in sorted((args.run / "eval").glob("step-*")):  # step-<7 digits>: in step order
        policy = load_policy(folder / "policy.pt").eval()
        windows = windows_of(policy, FeatureCache(dataset, policy, progress=False, store=True), SKILL_WINDOWS,
                             args.seed)
        skill = vision_skill(policy, windows, buckets=1, seed=args.seed, batch_size=args.batch_size)
        print(f"| {int(folder.name.removeprefix('step-'))} | {skill['joint_sample']['skill']:+.3f} |", flush=True)


if __name__ == "__main__":
    main()
