"""The world model's skill (``wm/skill``) of every periodic evaluation of a training run, computed anew.

Runs trained before the skill windows were put in the trunk's units at every evaluation logged a skill measured on
condition tokens of the untrained condition layers (-0.68 where the weights' own was +0.67). Each evaluation's
policy file is in ``eval/step-<N>/``; this scores it on the windows training scores (``SKILL_WINDOWS`` of the
training dataset, drawn with the run's seed; dataset, seed, batch size and cached views read from its
``config.json``) and prints one line per evaluation.

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
from dust_rl.diagnose.world_model import vision_skill, windows_of
from dust_rl.train.imitation import SKILL_WINDOWS
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
        windows = windows_of(policy, features, SKILL_WINDOWS, run["seed"])
        skill = vision_skill(policy, windows, buckets=1, seed=run["seed"], batch_size=run["optim"]["batch_size"])
        print(f"| {int(folder.name.removeprefix('step-'))} | {skill['joint_sample']['skill']:+.3f} |", flush=True)


if __name__ == "__main__":
    main()
