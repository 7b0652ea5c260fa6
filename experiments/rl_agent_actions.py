"""What a fine-tuned RL agent (``dust-rl finetune``, steer or residual) does at the first step of some episodes.

Why: a fine-tuning run can lose success while its losses look fine; the agent's own actions say why. For a SAC
agent the mean before the tanh shows whether it has run to the edges of its action box (|mean| >> 2: every
action saturated, the fixed std no longer explores, the tanh passes no gradient); for any agent the
deterministic action shows how far it has moved from the base policy (0 is the base policy's own action).

    .venv/bin/python experiments/rl_agent_actions.py --run runs/ft/RUN [--seeds 10000 10001]
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import numpy as np
import torch
from stable_baselines3 import SAC

from dust_rl.agents import load_policy
from dust_rl.rl.config import rl_config_from_json
from dust_rl.rl.finetune import RL_AGENT_KIND, build_agent, finetune_env_factory
from dust_rl.storage.checkpoint_files import load_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=pathlib.Path, required=True, help="a dust-rl finetune run folder")
    parser.add_argument("--seeds", type=int, nargs="+", default=[10000, 10001])
    args = parser.parse_args()
    torch.set_num_threads(1)
    saved = load_checkpoint(args.run / "rl_agent.pt", RL_AGENT_KIND)
    config = rl_config_from_json(saved["config"])
    config = dataclasses.replace(config, runtime=dataclasses.replace(config.runtime, device="cpu", progress=False))
    env = finetune_env_factory(config, load_policy(config.policy))[0]()
    agent = build_agent(config, env)
    agent.policy.load_state_dict(saved["state_dict"])
    for seed in args.seeds:
        obs, _ = env.reset(seed=seed)
        action = agent.predict(obs, deterministic=True)[0]
        line = (f"seed {seed}: deterministic action |mean| {np.abs(action).mean():.3f}, first entries "
                f"{np.array2string(action[:7], precision=3)}")
        if isinstance(agent, SAC):
            with torch.no_grad():
                mean, log_std, _ = agent.actor.get_action_dist_params(agent.policy.obs_to_tensor(obs)[0])
            mean = mean[0].numpy()
            line += (f"; before the tanh: |mean| {np.abs(mean).mean():.2f} (range {mean.min():.1f}..{mean.max():.1f}), "
                     f"{(np.abs(mean) > 2).mean():.0%} of {mean.size} beyond 2, std {log_std.exp().mean():.2f}")
        print(line)
    env.close()


if __name__ == "__main__":
    main()
