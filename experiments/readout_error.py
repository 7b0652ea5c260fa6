"""How far is a policy's object-state read-out from the truth, by time in the episode?

A policy trained with ``--model.lambda-aux`` estimates the privileged object state
from its keypoints or frozen tokens. On expert demonstrations the gripper sits on the
target cube for most of an episode, so an estimate that merely follows the gripper
scores well on average; the table separates the steps where the gripper is still far
from the target (the ones that decide where the arm goes) from the rest. The first
columns of ``observation.environment_state`` must be the named object's xyz, then the
next object's ``columns`` on (3 for the Franka pick and place tasks, 4 for press_button:
xyz and depression per button); the last two columns tell a read-out that finds the
objects but not which one is named (its target estimate then sits near the other one).
Run on a trained policy here; ``experiments/token_readout_probe.py`` prints the same table for a read-out fitted
alone.

    .venv/bin/python experiments/readout_error.py --policy runs/train/T/policy.pt --dataset runs/data/T_val
"""

from __future__ import annotations

import argparse

import torch

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import FeatureCache
from dust_rl.envs.env import STATE_PARTS
from dust_rl.keys import ENV_STATE_KEY, STATE_KEY

STEP_BUCKETS = ((0, 1), (1, 10), (10, 30), (30, 60), (60, 10**6))
EE_BLOCK = len(STATE_PARTS)  # the state ends with the end effector's position, quaternion and opening
TARGET_XY = slice(0, 2)  # the named object's xy in the object state


def readout_error_table(policy: DustPolicy, dataset: DemoDataset, norm: EnvStateNorm, columns: int = 3) -> str:
    """A markdown table of the read-out's xy errors (cm) on ``dataset``'s rows, by step of the episode.

    Args:
        policy: a policy with a state read-out.
        dataset: demonstrations from other seeds than the training data.
        norm: what normalised the object state in training (the training data's statistics); ``dataset``'s
            tasks must be among its tasks.
        columns: object-state columns per object.
    """
    cache = FeatureCache(dataset, policy, progress=False)
    windows = list(DemoWindows(dataset, horizon=policy.config.horizon, images=False).iterate(512))
    task = norm.task_indices(dataset.tasks)[dataset.row_task_index]
    estimate = norm.denormalize(torch.cat([policy.estimate_env_state(cache.batch(w)) for w in windows]), task)
    objects = torch.cat([w.get(ENV_STATE_KEY) for w in windows]).float()
    other_xy = slice(columns, columns + 2)
    target, other = objects[:, TARGET_XY], objects[:, other_xy]
    gripper = torch.cat([w.get(STATE_KEY) for w in windows]).float()[:, -EE_BLOCK:-EE_BLOCK + 2]
    step = torch.arange(len(dataset)) - torch.repeat_interleave(dataset.episode_starts, dataset.lengths)
    lines = ["| steps | rows | estimate to target (cm) | estimate to gripper (cm) | gripper to target (cm) | "
             "estimate to the next object (cm) | next object's estimate to it (cm) |", "|---|---|---|---|---|---|---|"]
    for low, high in STEP_BUCKETS:
        m = (step >= low) & (step < high)
        if m.any():
            def cm(a: torch.Tensor, b: torch.Tensor, m: torch.Tensor = m) -> float:
                return 100 * (a[m] - b[m]).norm(dim=1).mean().item()

            name = f"{low}+" if high > 10**5 else str(low) if high == low + 1 else f"{low}-{high - 1}"
            lines.append(f"| {name} | {int(m.sum())} | {cm(estimate[:, TARGET_XY], target):.1f} | "
                         f"{cm(estimate[:, TARGET_XY], gripper):.1f} | {cm(gripper, target):.1f} | "
                         f"{cm(estimate[:, TARGET_XY], other):.1f} | {cm(estimate[:, other_xy], other):.1f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="policy.pt trained with --model.lambda-aux")
    parser.add_argument("--dataset", required=True, help="demonstrations from other seeds than the training data")
    parser.add_argument("--columns", type=int, default=3, help="object-state columns per object (press_button: 4)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.policy)
    print(readout_error_table(policy, DemoDataset(args.dataset), EnvStateNorm.of_policy(policy), args.columns))


if __name__ == "__main__":
    main()
