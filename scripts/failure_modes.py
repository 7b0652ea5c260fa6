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

``--sheet PNG`` also draws, for the first episodes of each class, the cameras at four moments of the
episode (its last step included), so the classes can be looked at, not only counted.

    .venv/bin/python scripts/failure_modes.py --policy runs/train/T/policy.pt --seed 5000 --episodes 30 \
        [--max-steps N] [--sheet runs/eval/T/failure_modes.png]
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib

import matplotlib
import torch
from tensordict import TensorDictBase

from dust_rl.envs.tasks.pick_place import CUBE_HALF, PLATE_RADIUS
from dust_rl.evaluate import EvalConfig, evaluate_task, prepare
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

MOVED = 0.01  # m
LIFTED = CUBE_HALF + 0.02  # m: the task's own "lifted" height of the cube's centre
MODES = ("success", "wrong cube", "untouched", "not lifted", "held at the end", "dropped off the plate",
         "on the plate, not released")
MOMENTS = (0.25, 0.5, 0.75, 1.0)  # fractions of an episode drawn on the sheet


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


def contact_sheet(trajectories: dict[int, TensorDictBase], modes: dict[int, str], cameras: tuple[str, ...],
                  per_mode: int, path: pathlib.Path) -> None:
    """One row per episode (the first ``per_mode`` of each class), the cameras side by side at each moment."""
    rows = [(seed, mode) for mode in MODES for seed in [s for s, m in modes.items() if m == mode][:per_mode]]
    figure, axes = plt.subplots(len(rows), len(MOMENTS), figsize=(2.4 * len(cameras) * len(MOMENTS), 2.6 * len(rows)),
                                squeeze=False)
    for (seed, mode), row in zip(rows, axes):
        trajectory = trajectories[seed]
        for moment, axis in zip(MOMENTS, row):
            step = round(moment * (trajectory.shape[0] - 1))
            views = [trajectory[step].get((*IMAGE_KEY, camera)).permute(1, 2, 0) for camera in cameras]
            axis.imshow(torch.cat(views, dim=1).numpy())
            axis.set_title(f"seed {seed}, {mode}, step {step}" if moment == MOMENTS[0] else f"step {step}",
                           fontsize=8)
            axis.axis("off")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-steps", type=int, default=None, help="time limit per episode (default: the task's)")
    parser.add_argument("--sheet", type=pathlib.Path, default=None, help="also draw the episodes into this PNG")
    parser.add_argument("--per-class", type=int, default=3, help="episodes per class on the sheet")
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
    for mode in MODES:
        print(f"  {mode}: {counts[mode]}")
    print(json.dumps(modes))
    if args.sheet:
        contact_sheet(trajectories, modes, policy.cameras, args.per_class, args.sheet)
        print(f"sheet: {args.sheet}")


if __name__ == "__main__":
    main()
