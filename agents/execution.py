"""Receding-horizon execution of action chunks with torchrl's MultiStepActorWrapper.

The policy samples a chunk of H actions; the env executes the first
``execute_steps`` of them, one per step, then the policy re-plans from the
newest observation (paper and GR00T: execute part of each chunk). The
wrapper caches the chunk in the rollout's TensorDict and re-queries the
policy when its step counter reaches ``execute_steps`` or the env was reset
(``is_init``, from torchrl's ``InitTracker`` transform, which the env needs; without it
the executor raises a one-line error naming the transform).
With a vision stream the predicted future is cached the same way, so every
executed step carries ``("dust", "future_tokens")``: the future predicted at
its latest re-plan.

Given a ``seed_key``, the executor also restarts its sampling noise from the
episode's seed at every reset (:func:`episode_generator`), so an episode's
outcome depends on its seed only, whatever the number of env processes and
the order they ran their episodes in.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.modules import MultiStepActorWrapper
from torchrl.modules.vla import VLAWrapperBase

from dust_rl.errors import UserError
from dust_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, FUTURE_CHUNK_KEY, PREDICTED_FUTURE_KEY


def replans(step: int, execute_steps: int) -> bool:
    """Whether a chunk is sampled before env step ``step`` of an episode (0: the reset's): the receding-horizon rule,
    at the reset and every ``execute_steps`` steps after. :class:`ChunkExecutor` runs by it (torchrl's
    ``replan_interval``, checked against this function in the tests); the residual env asks it here."""
    return step % execute_steps == 0


def episode_generator(seed: int) -> torch.Generator:
    """The sampling-noise generator of the episode reset with ``seed``."""
    return torch.Generator().manual_seed(int(seed))


class ChunkExecutor(MultiStepActorWrapper):
    """``MultiStepActorWrapper`` over a chunk policy that also accepts unbatched envs.

    Built by :meth:`~dust_rl.agents.DustPolicy.executor`; it reads the policy's ``chunk_size`` and
    ``writes_future`` only, so this module does not import the policy.

    torchrl 0.14.1's wrapper assumes a leading batch dim: with an unbatched env (batch size ``[]``)
    it would emit a ``[1, action_dim]`` action. Unbatched inputs get a batch dim of one here.

    Args:
        policy: the chunk policy (a :class:`~dust_rl.agents.DustPolicy`).
        execute_steps: actions executed per chunk before re-planning, in [1, H].
        seed_key: where the env writes its episode seed (e.g. ``"episode_seed"``); at every reset the noise
            then restarts from it. None: the noise comes from torch's global generator.
    """

    def __init__(self, policy: VLAWrapperBase, execute_steps: int, seed_key: NestedKey | None = None) -> None:
        keys = {}
        if policy.writes_future:  # the predicted future travels with the chunk (see DustPolicy.forward)
            keys = {"action_keys": [ACTION_KEY, PREDICTED_FUTURE_KEY],
                    "chunk_keys": [ACTION_CHUNK_KEY, FUTURE_CHUNK_KEY]}
        super().__init__(policy, n_steps=policy.chunk_size, replan_interval=execute_steps, **keys)
        self.seed_key = seed_key
        self.generator = episode_generator(0)

    @property
    def in_keys(self) -> list[NestedKey]:
        return super().in_keys + ([] if self.seed_key is None else [self.seed_key])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.init_key not in tensordict.keys(include_nested=True):  # torchrl's own error names no fix
            raise UserError(f"the env gives the policy no {self.init_key!r} entry, so it cannot tell when an episode "
                            "starts; append torchrl's InitTracker to the env: TransformedEnv(env, InitTracker())")
        if self.seed_key is None:
            return self._execute(tensordict)
        if tensordict.get("is_init").any():
            self.generator = episode_generator(int(tensordict.get(self.seed_key)))
        with torch.random.fork_rng(devices=[]):  # the policy draws from the global generator: lend it ours
            torch.set_rng_state(self.generator.get_state())
            out = self._execute(tensordict)
            self.generator.set_state(torch.get_rng_state())
        return out

    def _execute(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims:
            return super().forward(tensordict)
        return tensordict.update(super().forward(tensordict.unsqueeze(0)).squeeze(0))

    def __getstate__(self) -> dict:
        # A torch.Generator pickles its state as a fresh tensor, which torch's default ``file_descriptor`` sharing
        # cannot rebuild in a collector's worker ("unable to resize file"): the state travels as plain bytes.
        state = super().__getstate__()
        state["generator"] = self.generator.get_state().numpy().tobytes()
        return state

    def __setstate__(self, state: dict) -> None:
        generator = torch.Generator()
        generator.set_state(torch.frombuffer(bytearray(state["generator"]), dtype=torch.uint8))
        super().__setstate__({**state, "generator": generator})

