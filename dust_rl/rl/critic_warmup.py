"""PPO whose actor waits at the base policy while its critic learns the base policy's values.

Why: a fine-tuning run starts with a random value function, and SB3's PPO normalises each minibatch's
advantages, so the first actor updates are full-sized steps along whatever the random critic says. Measured on
push (residual PPO from the 58% action-only policy, dense reward, SB3's defaults, `dust-rl finetune ...
--initial-std 0.1`): the training episodes' success fell from 61% in the first rollout to 47% by the sixth,
each update moving the policy by an approximate KL of about 0.04 with 40% of its ratios clipped. Fitting the
critic first on rollouts of the unchanged actor (the policy-evaluation warm-up of fine-tuning recipes such as
PA-RL and DPPO) gives the first actor update advantages of a fitted value function. It removes one cause of the
decline, not all: on the same base with ``--lr 1e-4 --target-kl 0.01 --critic-warmup 10240`` the
rollouts held 52-56% through the warm-up and then still fell, more slowly, to 38-44% after 45k env steps
(BENCHMARKS.md, "Push: residual PPO and steering PPO").

The actor's layers are switched off (``requires_grad``) at the end of every rollout whose last step is within the
warm-up, and on after it: the switch depends on the step count alone, so a resumed run (whose step count
comes back with its checkpoint) switches at the same rollout. The optimiser skips parameters without gradients.
"""

from __future__ import annotations

from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback


class CriticWarmup(BaseCallback):
    """Keep a PPO agent's actor fixed for its first ``env_steps`` (whole rollouts); its critic learns throughout.

    Args:
        env_steps: steps of the warm-up; a rollout that ends at or before it trains the critic only.
    """

    def __init__(self, env_steps: int) -> None:
        super().__init__()
        self.env_steps = env_steps

    def _init_callback(self) -> None:
        if not isinstance(self.model, PPO):
            raise TypeError(f"CriticWarmup needs a PPO agent, not {type(self.model).__name__}")

    def _on_rollout_end(self) -> None:
        policy = self.model.policy
        learning = self.num_timesteps > self.env_steps
        for module in (policy.mlp_extractor.policy_net, policy.action_net):
            module.requires_grad_(learning)

    def _on_step(self) -> bool:
        return True
