"""Act on K sampled chunks, not one: the one carrying the gripper nearest the read-out's target, or their mean.

Why: on stack the base policy's outcome turns on its sampling noise (``experiments/noise_headroom.py``: a perfect
chooser
among 4 draws wins 66% of the layouts against 34% for one draw, 54% when the draws part only once the cube is
carried). Two choosers that need no training test whether what the policy sees can make that choice:

- ``nearest``: while the gripper holds something (opening below ``--holding-below``), execute the sample whose
  planned displacement over the executed steps ends nearest in xy to the read-out's current estimate of the target
  (``--target-columns``, e.g. stack's lower cube: 3 4); otherwise the first sample, as the plain policy would.
- ``mean``: execute the mean of the K chunks (the conditional mean rather than one draw).

    .venv/bin/python experiments/chunk_choice.py --policy runs/train/T/policy.pt --rule nearest|mean [--k 4] \
        [--target-columns 3 4] [--seed 5000] [--episodes 50]
"""

from __future__ import annotations

import argparse

import torch
from in_process_eval import PlanHook, add_eval_arguments, prepare_in_process, success_line
from tensordict import TensorDict

from dust_rl.agents import DustPolicy
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.evaluate.closed_loop import evaluate_task

EE_POSITION, EE_OPENING = slice(-8, -5), -1  # the robot state ends with the gripper's position, quaternion, opening


class ChunkChoice(PlanHook):
    """While in a ``with`` block, the policy plans K samples per re-plan and executes one chunk chosen by ``rule``."""

    def __init__(self, policy: DustPolicy, rule: str, k: int, target_columns: list[int], holding_below: float) -> None:
        super().__init__(policy)
        self.rule, self.k = rule, k
        self.target_columns, self.holding_below = target_columns, holding_below
        self.norm = EnvStateNorm.of_policy(policy)
        self.chosen = self.plans = 0

    def _plan_features(self, features: TensorDict, generator: torch.Generator | None = None,
                       action_noise: torch.Tensor | None = None) -> TensorDict:
        samples = [self.plan_features(features, generator, action_noise) for _ in range(self.k)]
        chunks = torch.stack([s.get("action_chunk")[0] for s in samples])  # [K, H, Da], env units
        out, self.plans = samples[0], self.plans + 1
        if self.rule == "mean":
            return out.set("action_chunk", chunks.mean(0, keepdim=True))
        normalizer = self.policy.normalizer
        robot = (features.get("state") * normalizer.state_std + normalizer.state_mean)[0]
        if robot[EE_OPENING] >= self.holding_below:
            return out
        estimate = self.norm.denormalize(self.policy.estimate_env_state(features), torch.zeros(1, dtype=torch.long))
        target = estimate[0, self.target_columns]
        steps = self.policy.execute_steps
        ends = robot[EE_POSITION][:2] + chunks[:, :steps, :2].clamp(-1, 1).sum(1) * MAX_TRANSLATION
        self.chosen += 1
        return samples[int((ends - target).norm(dim=-1).argmin())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)
    parser.add_argument("--rule", choices=("nearest", "mean"), required=True)
    parser.add_argument("--k", type=int, default=4, help="samples per re-plan")
    parser.add_argument("--target-columns", type=int, nargs=2, default=[3, 4],
                        help="object-state columns of the target's x and y (stack: the lower cube)")
    parser.add_argument("--holding-below", type=float, default=0.06,
                        help="gripper opening (m) under which it holds something (Franka: 0.08 open, ~0.04 on a cube)")
    args = parser.parse_args()
    if args.k < 1:
        parser.error("--k needs K >= 1")
    policy, setup, config = prepare_in_process(args)
    if args.rule == "nearest" and not policy.config.aux_state_dim:
        raise SystemExit("--rule nearest needs a policy with a state read-out (--model.lambda-aux)")
    for task in setup.tasks:
        with ChunkChoice(policy, args.rule, args.k, args.target_columns, args.holding_below) as choice:
            episodes, _, _, _ = evaluate_task(setup, task, policy, config)
        chosen = f"; a chosen chunk at {choice.chosen} of {choice.plans} re-plans" if args.rule == "nearest" else ""
        print(f"{args.policy}, {args.rule} of K = {args.k}, seeds {args.seed}..{args.seed + args.episodes - 1}: "
              f"{success_line(task, episodes)}{chosen}", flush=True)


if __name__ == "__main__":
    main()
