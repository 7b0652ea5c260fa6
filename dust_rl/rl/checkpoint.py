"""An SB3 agent's learning state as tensors, so torchrl's ``Checkpoint`` can save and restore it.

SB3's own ``save`` / ``save_replay_buffer`` write pickles, and loading a
pickle runs code; this project loads nothing that way. :class:`SB3LearningState`
gives torchrl's ``Checkpoint`` a ``state_dict`` of tensors and numbers only:
the policy's networks (actor, critics, target critics), every optimiser, SAC's
entropy coefficient, the step and update counters and, for off-policy agents,
the filled part of the replay buffer. Restored into an agent built with the
same settings, training goes on from the saved step with nothing lost or
counted twice; the env starts a new episode there (its simulator state is not
saved), so a resumed run is not bit-identical to one never interrupted.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import DictReplayBuffer

BUFFER_FIELDS = ("actions", "rewards", "dones", "timeouts")


class SB3LearningState:
    """``state_dict`` / ``load_state_dict`` of everything an SB3 agent (SAC, PPO) learns from.

    Args:
        agent: the agent; ``load_state_dict`` writes into it.
    """

    def __init__(self, agent: BaseAlgorithm) -> None:
        self.agent = agent

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        agent = self.agent
        found = {name: getattr(module, "optimizer", None)
                 for name, module in (("actor", getattr(agent, "actor", None)),
                                      ("critic", getattr(agent, "critic", None)), ("policy", agent.policy))}
        found["ent_coef"] = getattr(agent, "ent_coef_optimizer", None)
        return {name: opt for name, opt in found.items() if opt is not None}

    def state_dict(self) -> dict:
        agent = self.agent
        state = {"policy": agent.policy.state_dict(),
                 "optimizers": {name: opt.state_dict() for name, opt in self._optimizers().items()},
                 "counters": {"num_timesteps": agent.num_timesteps, "n_updates": agent._n_updates,
                              "episode_num": agent._episode_num}}
        if getattr(agent, "log_ent_coef", None) is not None:
            state["log_ent_coef"] = agent.log_ent_coef.detach().clone()
        buffer = getattr(agent, "replay_buffer", None)
        if isinstance(buffer, DictReplayBuffer):
            size = buffer.buffer_size if buffer.full else buffer.pos
            state["replay_buffer"] = {
                "pos": buffer.pos, "full": buffer.full,
                **{f: torch.from_numpy(getattr(buffer, f)[:size].copy()) for f in BUFFER_FIELDS},
                "observations": {k: torch.from_numpy(v[:size].copy()) for k, v in buffer.observations.items()},
                "next_observations": {k: torch.from_numpy(v[:size].copy())
                                      for k, v in buffer.next_observations.items()},
            }
        return state

    def load_state_dict(self, state: dict) -> None:
        """Write ``state`` into the agent.

        Raises:
            ValueError: the state does not fit this agent (other networks, optimisers or buffer).
        """
        agent = self.agent
        agent.policy.load_state_dict(state["policy"])
        optimizers = self._optimizers()
        if set(optimizers) != set(state["optimizers"]):
            raise ValueError(f"optimisers {sorted(state['optimizers'])} saved, this agent has {sorted(optimizers)}")
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        counters = state["counters"]
        agent.num_timesteps, agent._n_updates = int(counters["num_timesteps"]), int(counters["n_updates"])
        agent._episode_num = int(counters["episode_num"])
        if "log_ent_coef" in state:
            with torch.no_grad():
                agent.log_ent_coef.copy_(state["log_ent_coef"])
        if "replay_buffer" in state:
            self._load_buffer(state["replay_buffer"])

    def _load_buffer(self, saved: dict) -> None:
        buffer = self.agent.replay_buffer
        size = len(saved["rewards"])
        if size > buffer.buffer_size or set(saved["observations"]) != set(buffer.observations):
            raise ValueError("the saved replay buffer does not fit this agent's")
        for f in BUFFER_FIELDS:
            getattr(buffer, f)[:size] = np.asarray(saved[f])
        for name in ("observations", "next_observations"):
            for key, values in saved[name].items():
                getattr(buffer, name)[key][:size] = np.asarray(values)
        buffer.pos, buffer.full = int(saved["pos"]), bool(saved["full"])
