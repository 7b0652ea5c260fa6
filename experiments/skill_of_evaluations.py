"""The world model's skill (``wm/skill``) of every periodic evaluation of a training run, computed anew.

Runs trained before the skill windows were put in the trunk's units at every evaluation logged a skill measured on
condition tokens of the untrained condition layers (-0.68 where the weights' own was +0.67). Each evaluation's
policy file is in ``eval/step-<N>/``; this scores it as training now does (``world_model_skill``; dataset, seed,
batch size and cached views read from the run's ``config.json``) and prints one line per evaluation.

    .venv/bin/python experiments/skill_of_evaluations.py --run runs/study/curve_all_dust
"""

from __future__ import annotations

import argparse
import json
import pathlib

import torch

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset
from dust_rl.data.features import FeatureCache
from dust_rl.train.imitation import world_model_skill
from dust_rl.train.settings import grouped_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=pathlib.Path, required=True, help="a `dust-rl train` run folder")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    run = grouped_json(json.loads((args.run / "config.json").read_text())["config"])
    dataset = DemoDataset(pathlib.Path(run["dataset"]), cache_dir=run.get("cache_dir"))
    print("| step | wm/skill |\n|---|---|")
    for folder in sorted((args.run / "eval").glob("step-*")):  # step-<7 digits>: in step order
        policy = load_policy(folder / "policy.pt").eval()
        features = FeatureCache(dataset, policy, progress=False, store=True,
                                views=run["data"].get("augment_views", 1))
        skill = world_model_skill(policy, features, run["seed"], run["optim"]["batch_size"])
        print(f"| {int(folder.name.removeprefix('step-'))} | {skill:+.3f} |", flush=True)


if __name__ == "__main__":
    main()
