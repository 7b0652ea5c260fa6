"""Start an SB3 agent at the base policy: zero mean action, small exploration, no uniform warm-up.

Residual RL and noise steering leave the base policy recoverable at the RL action 0 (no residual; the noise at the
centre of the base policy's own). SB3 starts far from it: a randomly initialised mean, a pre-tanh standard
deviation near 1, and for SAC ``learning_starts`` steps of uniformly random actions. On pick_place that is fatal:
the residual SAC run on a policy that solves 32-54% of episodes (docs/franka_results.md, "The recipe at 50 episodes
per seed set") succeeded in none of its first 24 training episodes, so a sparse reward never arrived. Residual-RL work
on manipulation starts the residual at zero with small exploration for this reason (ResiP, Ankile et al. 2024;
Policy Decorator, Yuan et al. 2024).

:func:`start_at_base` zeroes the layer that outputs the mean action and fixes the exploration standard deviation;
:class:`WarmStartSAC` acts with that actor from the first step (its warm-up steps still fill the replay buffer
before any update, but with the actor's actions, not uniform ones). The standard deviation is fixed, not learnt:
while the sparse reward is still 0 everywhere, SAC's entropy term alone drives a learnt one, and on pick_place it
grew from 0.1 to ~0.9 (pre-tanh) within 4,000 updates, with the initial entropy coefficient at 1.0 and at 0.01
alike. At 0.1 the base policy's episodes survive (2/8 validation episodes against 3/8 without any residual); at
1.0 none does (0/8).

With the std fixed, SAC's entropy bonus must go too (``dust-rl finetune`` sets ``ent_coef=0``): it adds
``-alpha * log_prob`` to every step's reward, and a tanh-Gaussian of pre-tanh std 0.1 has a log-density of about
+0.9 per action dimension, so in the steering env of a press_button policy (112 noise dimensions) every step paid
about -100 at alpha 0.8-1 against a sparse reward of 0 or 1. There the critic's loss grew from 270 to 2,400 within
1,000 updates and 2,000 steps of steering SAC left the policy where it was (32% -> 34% on 50 held-out seeds).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import ActionNoise

from dust_rl.rl.steering import prior_latents


class WarmStartSAC(SAC):
    """SAC whose warm-up steps (``learning_starts``, no updates yet) act with its actor instead of uniformly."""

    def _sample_action(self, learning_starts: int, action_noise: ActionNoise | None = None,
                       n_envs: int = 1) -> tuple[np.ndarray, np.ndarray]:
        return super()._sample_action(0, action_noise, n_envs)


class BaseWarmupSAC(SAC):
    """Steering SAC whose warm-up steps act with the base policy's own latents
    (:func:`~dust_rl.rl.steering.prior_latents` at ``noise_bound``) instead of uniformly: its replay buffer starts
    with the base policy's rollouts, as far as a latent can reproduce them (exactly, without a latent, up to the
    clipping and the fixed vision noise)."""

    noise_bound: float = 1.0
    """The steering env's: set after building the agent."""

    def _sample_action(self, learning_starts: int, action_noise: ActionNoise | None = None,
                       n_envs: int = 1) -> tuple[np.ndarray, np.ndarray]:
        if self.num_timesteps >= learning_starts:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        action = prior_latents(n_envs, self.action_space.shape[0], self.noise_bound).numpy()
        return action, self.policy.scale_action(action)


def check_initial_std(std: float) -> None:
    """Raise ValueError unless ``std`` is a finite number > 0."""
    if not (math.isfinite(std) and std > 0):
        raise ValueError(f"the initial exploration std must be a finite number > 0, got {std}")


def start_at_base(agent: BaseAlgorithm, std: float, learn_std: bool = False) -> None:
    """Make ``agent``'s mean action 0 for every observation and its exploration standard deviation ``std``, fixed.

    SAC: ``std`` is before the tanh squashing (the action is ``tanh`` of a Gaussian), and the agent should be built
    with ``ent_coef=0`` (as ``dust-rl finetune`` does; the module docstring says why). PPO: of the Gaussian itself.
    ``learn_std``: the std only starts at ``std`` (SAC with a learnt entropy coefficient and target, which holds
    it where the fixed std's reasons above do not apply).

    Raises:
        ValueError: ``std`` is not a finite positive number.
        TypeError: an algorithm other than SAC or PPO.
    """
    check_initial_std(std)
    with torch.no_grad():
        if isinstance(agent, SAC):
            mean, log_std = agent.actor.mu, agent.actor.log_std
            log_std.weight.zero_()
            log_std.bias.fill_(math.log(std))
        elif isinstance(agent, PPO):
            mean, log_std = agent.policy.action_net, agent.policy.log_std
            log_std.fill_(math.log(std))
        else:
            raise TypeError(f"start_at_base supports SAC and PPO, not {type(agent).__name__}")
        mean.weight.zero_()
        mean.bias.zero_()
    if not learn_std:
        log_std.requires_grad_(False)  # the optimisers skip parameters without gradients
