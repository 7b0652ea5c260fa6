"""Where pick_place episodes fail: each episode sorted by what happened to the two cubes.

Why: the success rate says how often a policy fails, not where; the videos show one episode. The
simulator's object positions (``observation.environment_state``: target cube, distractor cube, plate, xyz
each) are in every evaluated step, so each episode is sorted, from its trajectory alone, into the
first of

* ``success``;
* ``wrong cube``: the distractor moved more than 1 cm;
* ``untouched``: the target cube never moved more than 1 cm (the grasp missed it);
* ``not lifted``: the target moved but never rose 2 cm above the table;
* ``held at the end``: lifted, and still in the air when time ran out;
* ``dropped off the plate``: lifted, and at the end lying off the plate;
* ``on the plate, not released``: lifted and on the plate, the gripper still touching it.

    .venv/bin/python scripts/failure_modes.py --policy runs/train/T/policy.pt --seed 5000 --episodes 30 [--max-steps N]
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib

import torch

from dust_rl.envs.tasks.pick_place import CUBE_HALF, PLATE_RADIUS
from dust_rl.evaluate import EvalConfig, evaluate_task, prepare
from dust_rl.keys import ENV_STATE_KEY

MOVED = 0.01  # m
LIFTED = CUBE_HALF + 0.02  # m: the task's own "lifted" height of the cube's centre


def failure_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one episode from its object positions [T, 9] (target, distractor, plate)."""
    target, distractor, plate = env_state[:, 0:3], env_state[:, 3:6], env_state[:, 6:9]
    if success:
        return "success"
    if (distractor[:, :2] - distractor[0, :2]).norm(dim=-1).max() > MOVED:
        return "wrong cube"
    if (target - target[0]).norm(dim=-1).max() <= MOVED:
        return "untouched"
    if target[:, 2].max() <= LIFTED:
        return "not lifted"
    if target[-1, 2] > LIFTED:
        return "held at the end"
    if (target[-1, :2] - plate[-1, :2]).norm() >= PLATE_RADIUS - 0.01:  # the task's own on-plate radius
        return "dropped off the plate"
    return "on the plate, not released"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-steps", type=int, default=None, help="time limit per episode (default: the task's)")
    args = parser.parse_args()
    config = EvalConfig(policy=args.policy, seed=args.seed, episodes=args.episodes, workers=1, videos=args.episodes,
                        threads=args.threads, max_steps=args.max_steps, device="cpu")
    torch.set_num_threads(args.threads)
    policy, setup = prepare(config)
    if setup.tasks != ("pick_place",):
        raise SystemExit(f"{args.policy}: trained on {setup.tasks}; this script reads pick_place's objects")
    episodes, trajectories, _, _ = evaluate_task(setup, "pick_place", policy, config)
    modes = {e.seed: failure_mode(trajectories[e.seed].get(("next", *ENV_STATE_KEY)), e.success) for e in episodes}
    counts = collections.Counter(modes.values())
    print(f"{args.policy}, seeds {args.seed}..{args.seed + args.episodes - 1}:")
    for mode in ("success", "wrong cube", "untouched", "not lifted", "held at the end", "dropped off the plate",
                 "on the plate, not released"):
        print(f"  {mode}: {counts[mode]}")
    print(json.dumps(modes))


if __name__ == "__main__":
    main()
