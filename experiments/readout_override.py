"""What a read-out policy does with a corrected estimate: evaluate it with some of the estimate's columns replaced.

Why: a policy that feeds its read-out's object-state estimate to the trunk (``--model.aux-state-input``) can fail
because the estimate is off or because it acts imprecisely on a good one; replacing one object's columns tells the
two apart without training anything. ``--truth`` writes the simulator's object state (normalised as the read-out
was trained) into the columns at every re-plan; ``--hold K`` writes the estimate's mean over the episode's first K
re-plans (an object that stays put until touched is seen best before the gripper covers it). Caveat: the policy
was trained on the read-out's estimates, errors included, so a better estimate is still a shift from what it saw
(on stack, all nine columns true gave 5/50 against the unchanged policy's 17/50; docs/franka_results.md "stack").

    .venv/bin/python experiments/readout_override.py --policy runs/train/T/policy.pt --columns 3:6 --truth \
        [--hold K] [--seed 5000] [--episodes 50]

The columns are the task's ``environment_state`` layout (``dust_rl/envs/tasks/<task>.py``, e.g. stack: cube to
move, lower cube, distractor, xyz each). Prints the success rate with its 95% interval and the episodes' outcomes.
"""

from __future__ import annotations

import argparse
import json

import torch
from in_process_eval import add_eval_arguments, prepare_in_process, success_line
from tensordict import TensorDictBase
from torch import nn

from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.evaluate.closed_loop import evaluate_task
from dust_rl.keys import ENV_STATE_KEY


class EstimateOverride:
    """Forward hooks on a policy that replace columns ``lo:hi`` of its read-out's estimate (one env at a time).

    Args:
        norm: the normalisation the read-out was trained with.
        columns: the replaced columns.
        hold: None: the true state; K: the estimate's mean over the episode's first K re-plans.
    """

    def __init__(self, norm: EnvStateNorm, columns: slice, hold: int | None) -> None:
        self.norm, self.columns, self.hold = norm, columns, hold
        self.truth: torch.Tensor | None = None
        self.seen: list[torch.Tensor] = []

    def attach(self, policy: nn.Module) -> None:
        policy.register_forward_pre_hook(self.observe, with_kwargs=True)
        policy.state_readout.register_forward_hook(self.replace)

    def observe(self, module: nn.Module, args: tuple, kwargs: dict) -> None:
        """Before each re-plan: the true state, and a new episode's reset of the held estimates."""
        tensordict: TensorDictBase = args[0] if args else kwargs["tensordict"]
        if tensordict.get("is_init").any():
            self.seen = []
        state = tensordict.get(ENV_STATE_KEY).float().reshape(1, -1)
        self.truth = self.norm.normalize(state, torch.zeros(1, dtype=torch.long))

    def replace(self, module: nn.Module, args: tuple, estimate: torch.Tensor) -> torch.Tensor:
        if estimate.shape[0] != 1:
            raise RuntimeError(f"one env at a time: the read-out's batch is {estimate.shape[0]}")
        estimate = estimate.clone()
        if self.hold is None:
            estimate[:, self.columns] = self.truth[:, self.columns]
            return estimate
        if len(self.seen) < self.hold:
            self.seen.append(estimate[:, self.columns])
        estimate[:, self.columns] = torch.stack(self.seen).mean(0)
        return estimate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)
    parser.add_argument("--columns", required=True, help="lo:hi, the estimate's columns to replace")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--truth", action="store_true", help="the simulator's object state")
    source.add_argument("--hold", type=int, help="the estimate's mean over the episode's first K re-plans")
    args = parser.parse_args()
    lo, hi = (int(v) for v in args.columns.split(":"))
    if args.hold is not None and args.hold < 1:
        parser.error("--hold needs K >= 1")
    policy, setup, config = prepare_in_process(args)
    if len(setup.tasks) != 1 or not policy.config.aux_state_input:
        raise SystemExit(f"{args.policy}: needs a single-task policy that feeds its read-out to the trunk")
    width = policy.config.aux_state_dim
    if not 0 <= lo < hi <= width:
        parser.error(f"--columns {args.columns} outside the estimate's {width} columns")
    EstimateOverride(EnvStateNorm.of_policy(policy), slice(lo, hi), args.hold).attach(policy)
    episodes, _, _, _ = evaluate_task(setup, setup.tasks[0], policy, config)
    print(f"{args.policy}, columns {lo}:{hi} {'true' if args.truth else f'held over {args.hold} re-plans'}, seeds "
          f"{args.seed}..{args.seed + args.episodes - 1}: {success_line(setup.tasks[0], episodes)}")
    print(json.dumps({e.seed: e.success for e in episodes}))


if __name__ == "__main__":
    main()
