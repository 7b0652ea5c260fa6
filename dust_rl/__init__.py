"""dust-rl: DUST (dual-stream diffusion world-model VLA) for torchrl and gymnasium.

Importing the package registers the gymnasium environments
(``gymnasium.make("DustFranka-v0", task=...)``, ``"DustHumanoid-v0"``) and nothing heavier:
torch, MuJoCo's env classes and the agents load when first used, so a script that only needs
the ids or ``__version__`` does not wait for torch.
"""

from importlib import metadata

from dust_rl.envs.registration import register_envs

register_envs()

try:
    # The installed distribution's version: one number, kept in pyproject.toml.
    __version__ = metadata.version("dust-rl")
except metadata.PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"
