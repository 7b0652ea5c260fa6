"""torchrl view of the gymnasium envs, with the canonical VLA TensorDict keys.

Gymnasium observations use flat LeRobot-style names
(``observation.image.front``); torchrl's VLA schema nests them
(``("observation", "image", "front")`` as uint8 ``[C, H, W]``,
``("observation", "state")``, root ``language_instruction``). This module
only renames and permutes: the env itself is the gymnasium one, so both
worlds see identical episodes.
"""

from __future__ import annotations

from torchrl.envs import Compose, GymEnv, PermuteTransform, RenameTransform, TransformedEnv


def canonical_key(flat_key: str) -> str | tuple[str, ...]:
    """``"observation.image.front"`` -> ``("observation", "image", "front")``."""
    return tuple(flat_key.split(".")) if "." in flat_key else flat_key


def make_torchrl_env(env_id: str = "DustFranka-v0", **kwargs) -> TransformedEnv:
    """A torchrl ``GymEnv`` of ``env_id`` whose observations follow the VLA schema.

    Args:
        env_id: registered gymnasium id.
        **kwargs: forwarded to the environment (``task``, ``obs_mode``, ...).
    """
    import dust_rl  # noqa: F401  (registers the ids)

    base = GymEnv(env_id, **kwargs)
    flat_keys = [key for key in base.observation_spec.keys() if isinstance(key, str) and "." in key]
    image_keys = [canonical_key(k) for k in flat_keys if k.startswith("observation.image.")]
    transforms = [RenameTransform(in_keys=flat_keys, out_keys=[canonical_key(k) for k in flat_keys])]
    if image_keys:
        transforms.append(PermuteTransform(dims=[-1, -3, -2], in_keys=image_keys))
    return TransformedEnv(base, Compose(*transforms))
