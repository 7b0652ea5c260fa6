"""torchrl view of the gymnasium envs, with the canonical VLA TensorDict keys.

Gymnasium observations use flat LeRobot-style names
(``observation.image.front``); torchrl's VLA schema nests them
(``("observation", "image", "front")`` as uint8 ``[C, H, W]``,
``("observation", "state")``, root ``language_instruction``); state mode's
dot-free ``agent_pos`` / ``environment_state`` land on the same nested keys, and
its instruction (in ``info``) on ``language_instruction``. This module only
renames and permutes: the env itself is the gymnasium one, so both worlds see
identical episodes.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import Unbounded
from torchrl.envs import Compose, EnvBase, GymWrapper, PermuteTransform, RenameTransform, TransformedEnv

from dust_rl.keys import INSTRUCTION_KEY

from .env import STATE_MODE_KEYS

_FLAT_NAMES = {short: flat for flat, short in STATE_MODE_KEYS.items()}


def canonical_key(key: str) -> str | tuple[str, ...]:
    """The VLA key of a gymnasium key: ``"observation.image.front"`` -> ``("observation", "image", "front")``.

    State mode's dot-free names go through their flat names: ``"agent_pos"`` -> ``("observation", "state")``.
    """
    flat_key = _FLAT_NAMES.get(key, key)
    return tuple(flat_key.split(".")) if "." in flat_key else flat_key


def canonical_transforms(base: EnvBase) -> Compose:
    """Transforms that nest ``base``'s flat (or state-mode) observation keys into the VLA schema."""
    flat_keys = [key for key in base.observation_spec.keys() if isinstance(key, str) and canonical_key(key) != key]
    image_keys = [canonical_key(k) for k in flat_keys if k.startswith("observation.image.")]
    transforms = [RenameTransform(in_keys=flat_keys, out_keys=[canonical_key(k) for k in flat_keys])]
    if image_keys:
        transforms.append(PermuteTransform(dims=[-1, -3, -2], in_keys=image_keys))
    return Compose(*transforms)


def success_spec() -> Unbounded:
    """The spec of ``info["is_success"]`` (a bool), for torchrl's info reader, whose default spec is a float:
    ``GymEnv(...).set_info_dict_reader(default_info_dict_reader(["is_success"], spec=[success_spec()]))``."""
    return Unbounded((), dtype=torch.bool)


class InstructionObservation(gym.Wrapper):
    """State mode's instruction, which it gives in ``info``, also in the observation (as rgb mode has it), so
    torchrl sees it at ``language_instruction``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({**env.observation_space.spaces,
                                                  INSTRUCTION_KEY: env.unwrapped.instruction_space})

    def reset(self, **kwargs) -> tuple[dict, dict]:
        obs, info = self.env.reset(**kwargs)
        return {**obs, INSTRUCTION_KEY: info[INSTRUCTION_KEY]}, info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return {**obs, INSTRUCTION_KEY: info[INSTRUCTION_KEY]}, reward, terminated, truncated, info


def make_torchrl_env(env: str | gym.Env = "DustFranka-v0", **kwargs) -> TransformedEnv:
    """A torchrl env whose observations follow the VLA schema.

    Args:
        env: a registered gymnasium id, or an already built (possibly wrapped) gymnasium env.
        **kwargs: forwarded to the environment when ``env`` is an id (``task``, ``obs_mode``, ...).
    """
    if isinstance(env, str):  # without gymnasium's checker, as torchrl's GymEnv makes it
        env = gym.make(env, **{"disable_env_checker": True, **kwargs})
    if getattr(env.unwrapped, "obs_mode", None) == "state":
        env = InstructionObservation(env)
    base = GymWrapper(env)
    return TransformedEnv(base, canonical_transforms(base))
