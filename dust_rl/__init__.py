"""dust-rl: DUST (dual-stream diffusion world-model VLA) for torchrl and gymnasium.

Importing the package registers the gymnasium environments
(``gymnasium.make("DustFranka-v0", task=...)``, ``"DustHumanoid-v0"``).
"""

from dust_rl.envs.registration import register_envs

register_envs()

__version__ = "0.1.0"
