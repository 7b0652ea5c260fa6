"""Receding-horizon execution of action chunks with torchrl's MultiStepActorWrapper.

The policy samples a chunk of H actions; the env executes the first
``execute_steps`` of them, one per step, then the policy re-plans from the
newest observation (paper and GR00T: execute part of each chunk). The
wrapper caches the chunk in the rollout's TensorDict and re-queries the
policy when its step counter reaches ``execute_steps`` or the env was reset
(``is_init``, from torchrl's ``InitTracker`` transform, which the env needs).
With a vision stream the predicted future is cached the same way, so every
executed step carries ``("dust", "future_tokens")``: the future predicted at
its latest re-plan.
"""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.modules import MultiStepActorWrapper

from dust_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, FUTURE_CHUNK_KEY, PREDICTED_FUTURE_KEY

from .policy import DustPolicy


class ChunkExecutor(MultiStepActorWrapper):
    """``MultiStepActorWrapper`` over a :class:`DustPolicy` that also accepts unbatched envs.

    torchrl 0.14.1's wrapper assumes a leading batch dim: with an unbatched env (batch size ``[]``)
    it would emit a ``[1, action_dim]`` action. Unbatched inputs get a batch dim of one here.

    Args:
        policy: the chunk policy.
        execute_steps: actions executed per chunk before re-planning, in [1, H].
    """

    def __init__(self, policy: DustPolicy, execute_steps: int) -> None:
        keys = {}
        if policy.writes_future:  # the predicted future travels with the chunk (see DustPolicy.forward)
            keys = {"action_keys": [ACTION_KEY, PREDICTED_FUTURE_KEY],
                    "chunk_keys": [ACTION_CHUNK_KEY, FUTURE_CHUNK_KEY]}
        super().__init__(policy, n_steps=policy.chunk_size, replan_interval=execute_steps, **keys)

    @property
    def policy(self) -> DustPolicy:
        return self.actor

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims:
            return super().forward(tensordict)
        return tensordict.update(super().forward(tensordict.unsqueeze(0)).squeeze(0))
