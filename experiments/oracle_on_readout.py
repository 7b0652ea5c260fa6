"""A policy trained on the objects' true positions, run on another policy's read-out of them.

Why: on stack the oracle (trained and run with the true positions, ``dust-rl collect --privileged-state``)
succeeds 90-94% where the read-out policy succeeds 34-36%, and handing the read-out policy the truth at test time
does not help (``experiments/readout_override.py``). The other split of perception from control: keep the oracle's
control and give it, in place of the simulator's object state, the read-out's estimate (turned back into metres),
as a pose-estimation stage would feed a planner. Both policies must be of the same task and cameras. Prints the
success rate and the estimate's mean error per column of the object state (the task's layout, e.g. stack: cube to
move, lower cube, distractor, xyz each, metres).

    .venv/bin/python experiments/oracle_on_readout.py --policy runs/train/ORACLE/policy.pt \
        --readout runs/train/READOUT/policy.pt [--seed 5000] [--episodes 50]
"""

from __future__ import annotations

import argparse
import json
import pathlib

import torch
from in_process_eval import add_eval_arguments, prepare_in_process, success_line
from tensordict import TensorDictBase
from torch import nn

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.evaluate.closed_loop import evaluate_task
from dust_rl.keys import STATE_KEY


class ReadoutState:
    """A forward pre-hook that swaps the object state at the end of the observed state for ``readout``'s estimate."""

    def __init__(self, readout: DustPolicy) -> None:
        self.readout, self.norm = readout, EnvStateNorm.of_policy(readout)
        self.width = readout.config.aux_state_dim
        self.errors: list[torch.Tensor] = []  # |estimate - truth| per column at every re-plan, in the state's units

    @torch.no_grad()
    def __call__(self, module: nn.Module, args: tuple, kwargs: dict) -> None:
        tensordict: TensorDictBase = args[0] if args else kwargs["tensordict"]
        state = tensordict.get(STATE_KEY)
        robot = state[..., :-self.width]
        observed = tensordict.clone(recurse=False).set(STATE_KEY, robot)
        estimate = self.readout.estimate_env_state(self.readout.observation_features(observed))
        metres = self.norm.denormalize(estimate, torch.zeros(estimate.shape[0], dtype=torch.long))
        metres = metres.reshape(*robot.shape[:-1], -1).to(state.dtype)
        self.errors.append((metres - state[..., -self.width:]).abs().reshape(-1, self.width))
        tensordict.set(STATE_KEY, torch.cat([robot, metres], -1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)  # --policy: trained with --privileged-state
    parser.add_argument("--readout", type=pathlib.Path, required=True, help="a policy with a state read-out")
    args = parser.parse_args()
    policy, setup, config = prepare_in_process(args)
    readout = load_policy(args.readout).eval()
    if not setup.env_kwargs.get("privileged_state") or not readout.config.aux_state_dim:
        raise SystemExit("--policy must be trained with --privileged-state and --readout must have a state read-out")
    if tuple(readout.info.get("tasks", ())) != setup.tasks:
        raise SystemExit(f"the policies' tasks differ: {setup.tasks} and {readout.info.get('tasks')}")
    swap = ReadoutState(readout)
    policy.register_forward_pre_hook(swap, with_kwargs=True)
    episodes, _, _, _ = evaluate_task(setup, setup.tasks[0], policy, config)
    print(f"{args.policy} on the read-out of {args.readout}, seeds {args.seed}..{args.seed + args.episodes - 1}: "
          f"{success_line(setup.tasks[0], episodes)}")
    print("mean |estimate - truth| per object-state column over all re-plans:",
          " ".join(f"{v:.3f}" for v in torch.cat(swap.errors).mean(0).tolist()))
    print(json.dumps({e.seed: e.success for e in episodes}))


if __name__ == "__main__":
    main()
