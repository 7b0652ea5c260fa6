"""RL on top of a trained policy: the frozen-policy envs (noise steering, residual), the SB3 and torchrl
front-ends, and ``dust-rl finetune``'s methods."""
