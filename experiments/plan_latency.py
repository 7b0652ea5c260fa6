"""CPU time of one ``plan`` call (a whole chunk) of a trained policy on a real pick_place observation.

Process CPU time at one thread estimates the latency on an idle core even while other jobs share the
machine; the first :data:`WARMUP` calls are not counted.

    .venv/bin/python experiments/plan_latency.py runs/train/T/policy.pt
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium as gym
import torch
from tensordict import TensorDict

from dust_rl.agents import load_policy
from dust_rl.keys import INSTRUCTION_KEY

WARMUP, CALLS = 5, 25


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", help="policy.pt")
    parser.add_argument("--seed", type=int, default=5000, help="reset seed of the observation")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.policy).eval()
    env = gym.make("DustFranka-v0", task="pick_place")
    obs, _ = env.reset(seed=args.seed)
    env.close()
    numeric = {key: torch.from_numpy(value)[None] for key, value in obs.items() if key != INSTRUCTION_KEY}
    td = TensorDict(numeric, batch_size=[1]).set(INSTRUCTION_KEY, obs[INSTRUCTION_KEY])
    times = []
    for _ in range(CALLS):
        start = time.process_time()
        policy.plan(td)
        times.append(time.process_time() - start)
    print(f"{args.policy}: median {1000 * statistics.median(times[WARMUP:]):.1f} ms CPU per chunk "
          f"(best {1000 * min(times[WARMUP:]):.1f}), one thread")


if __name__ == "__main__":
    main()
