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

import numbers

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import DictReplayBuffer

from dust_rl.storage.checkpoint_files import check_tensor_values

BUFFER_FIELDS = ("actions", "rewards", "dones", "timeouts")
COUNTERS = ("num_timesteps", "n_updates", "episode_num")


class SB3LearningState:
    """``state_dict`` / ``load_state_dict`` of everything an SB3 agent (SAC, PPO) learns from.

    A checkpoint is written by whoever writes the run folder (its digests catch damage, not forgery), so what it
    restores is checked first: finite floats, counters that are counts, and a step counter that fits the run's
    budget and the replay buffer's fill.

    Args:
        agent: the agent; ``load_state_dict`` writes into it.
        steps: the run's budget of RL steps; a restored step counter past it (PPO: past the rollout that crossed it)
            is refused. None: not checked.
    """

    def __init__(self, agent: BaseAlgorithm, steps: int | None = None) -> None:
        self.agent = agent
        self.steps = steps

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
            ValueError: the state does not fit this agent (other networks, optimisers or buffer), holds NaN, infinity
                or integers where the agent holds floats, or counters that no run of this agent reaches.
        """
        agent = self.agent
        check_tensor_values(state["policy"], agent.policy.state_dict())
        counters = {name: _count(state["counters"], name) for name in COUNTERS}
        self._check_budget(counters["num_timesteps"])
        agent.policy.load_state_dict(state["policy"])
        optimizers = self._optimizers()
        if set(optimizers) != set(state["optimizers"]):
            raise ValueError(f"optimisers {sorted(state['optimizers'])} saved, this agent has {sorted(optimizers)}")
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        agent.num_timesteps, agent._n_updates, agent._episode_num = (counters[name] for name in COUNTERS)
        if "log_ent_coef" in state:
            check_tensor_values({"log_ent_coef": state["log_ent_coef"]}, {"log_ent_coef": agent.log_ent_coef})
            with torch.no_grad():
                agent.log_ent_coef.copy_(state["log_ent_coef"])
        if "replay_buffer" in state:
            self._load_buffer(state["replay_buffer"])

    def _check_budget(self, num_timesteps: int) -> None:
        """Raise ``ValueError`` when ``num_timesteps`` is past what a run of ``steps`` RL steps reaches: the budget,
        or for an on-policy agent the budget plus all but one step of a rollout (its last rollout may cross it)."""
        if self.steps is None:
            return
        rollout = getattr(self.agent, "n_steps", 1) * self.agent.n_envs
        if num_timesteps > self.steps + rollout - 1:
            raise ValueError(f"counters/num_timesteps is {num_timesteps}, past the run's {self.steps} steps")

    def _load_buffer(self, saved: dict) -> None:
        buffer = self.agent.replay_buffer
        size = len(saved["rewards"])
        if size > buffer.buffer_size or set(saved["observations"]) != set(buffer.observations):
            raise ValueError("the saved replay buffer does not fit this agent's")
        pos, full = saved["pos"], saved["full"]  # checked against the fill the step counter gives
        rows = self.agent.num_timesteps // buffer.n_envs  # every step of the envs together adds one row
        fill = (min(rows, buffer.buffer_size), rows >= buffer.buffer_size, rows % buffer.buffer_size)  # it wraps
        if self.agent.num_timesteps % buffer.n_envs or (size, full, pos) != fill:
            raise ValueError(f"the saved replay buffer (pos {pos!r}, full {full!r}, {size} rows) is not what "
                             f"{self.agent.num_timesteps} steps of {buffer.n_envs} env(s) fill in a buffer of "
                             f"{buffer.buffer_size} rows (pos {fill[2]}, full {fill[1]}, {fill[0]} rows)")
        check_tensor_values(_flat(saved), _flat({f: getattr(buffer, f) for f in (*BUFFER_FIELDS, "observations",
                                                                                 "next_observations")}))
        for f in BUFFER_FIELDS:
            getattr(buffer, f)[:size] = np.asarray(saved[f])
        for name in ("observations", "next_observations"):
            for key, values in saved[name].items():
                getattr(buffer, name)[key][:size] = np.asarray(values)
        buffer.pos, buffer.full = fill[2], fill[1]


def _count(counters: dict, name: str) -> int:
    """``counters[name]``, checked to be a count (an int >= 0)."""
    value = counters[name]
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= 0):
        raise ValueError(f"counters/{name} is {value!r}, not a count >= 0")
    return int(value)


def _flat(arrays: dict) -> dict[str, torch.Tensor]:
    """The replay buffer's arrays (or their saved copies) by name, an observation's as ``observations/<key>``, as
    tensors (numpy arrays shared, not copied)."""
    flat = {}
    for name, value in arrays.items():
        if isinstance(value, dict):
            flat |= {f"{name}/{key}": torch.as_tensor(v) for key, v in value.items()}
        elif isinstance(value, np.ndarray | torch.Tensor):
            flat[name] = torch.as_tensor(value)
    return flat
