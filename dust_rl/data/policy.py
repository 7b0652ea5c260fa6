"""The collector's policy: the scripted expert (optionally perturbed, DART), or a trained policy.

The env already computed the expert's action for the current state (see
``ExpertActionWrapper``); the policy only reads it. With ``noise_std > 0`` the
executed ``action`` is ``clip(expert_action + noise_std * eps)`` while the dataset
keeps ``expert_action`` as the label: the expert's correction from the perturbed
states it visits (Laskey et al., DART, 2017). The noise is drawn from a generator
seeded by (episode seed, step), so a noisy episode is reproducible from its seed.

A trained policy (:func:`load_rollout_policy`) runs as ``dust-rl eval`` runs it, so
its stored episodes are the ones evaluation would see from the same seeds; the env
still writes the expert's ``expert_action`` beside its ``action`` (DAgger's label).
"""

from __future__ import annotations

import pathlib

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from dust_rl.agents import ChunkExecutor, load_policy
from dust_rl.keys import EXPERT_ACTION_KEY, SEED_KEY, STEP_KEY
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.settings import RuntimeSettings


class ExpertPolicy(nn.Module):
    """``action = clip(expert_action + noise_std * eps(seed, step), -1, 1)``."""

    def __init__(self, noise_std: float = 0.0) -> None:
        super().__init__()
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std}")
        self.noise_std = float(noise_std)

    def forward(self, expert_action: torch.Tensor, seed: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        if self.noise_std == 0.0:
            return expert_action.clone()
        flat_action = expert_action.reshape(-1, expert_action.shape[-1])
        noise = torch.stack([
            torch.randn(flat_action.shape[-1], generator=torch.Generator().manual_seed(int(s) * 1_000_003 + int(t)))
            for s, t in zip(seed.reshape(-1).tolist(), step.reshape(-1).tolist())])
        return (flat_action + self.noise_std * noise).clamp(-1.0, 1.0).reshape(expert_action.shape)


def make_expert_policy(noise_std: float = 0.0) -> TensorDictModule:
    """The collector policy: reads ``expert_action``, ``episode_seed``, ``step_count``; writes ``action``."""
    return TensorDictModule(ExpertPolicy(noise_std), in_keys=[EXPERT_ACTION_KEY, SEED_KEY, STEP_KEY],
                            out_keys=["action"])


def load_rollout_policy(path: pathlib.Path, runtime: RuntimeSettings) -> ChunkExecutor:
    """The collector policy of a trained policy file, on ``runtime``'s device at its precision: reads the VLA
    observation keys, ``is_init`` and ``episode_seed``; writes ``action``. Raises ``CheckpointError`` for a missing
    or corrupt file."""
    policy = load_policy(path).to(resolve_device(runtime.device))
    policy.set_runtime(runtime.precision, runtime.compile)
    return policy.executor(seeded=True)
