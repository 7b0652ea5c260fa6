"""stable-baselines3 on the dust-rl envs as they are: observations SB3 accepts, and DUST's frozen image features.

SB3 has no space for text: on the image-mode env, whose instruction is a
gymnasium ``Text``, ``SAC("MultiInputPolicy", env)`` raises
``NotImplementedError``. :class:`SB3Observations` replaces the instruction
with its frozen embedding (the text encoder's tokens averaged, a float Box;
each distinct instruction is encoded once), drops the privileged object
state, writes the entries' dots as slashes (SB3 keeps one torch module per
entry, and module names cannot hold dots) and leaves the camera frames as
uint8 Boxes, so SB3's own CNN extractors run on pixels.
:class:`FrozenBackboneExtractor` maps each camera through a frozen image
encoder instead (the same encoders DUST conditions on; tokens averaged per
camera), beside the other entries flattened: no convolution to train, which
matters on a CPU.

Use: ``SAC("MultiInputPolicy", SB3Observations(env), policy_kwargs={"features_extractor_class":
FrozenBackboneExtractor, "features_extractor_kwargs": {"image_encoder": "efficientnet-lite0"}})``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import Tensor

from dust_rl.agents import ImageEncoder, TextEncoder, TransformersTextEncoder, pooled_text
from dust_rl.agents.encoders.backbone import resolve_image_encoder
from dust_rl.agents.encoders.image_encoder import image_tokens
from dust_rl.errors import ConfigError
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY, INSTRUCTION_KEY, flat_name

ENV_STATE_NAME = flat_name(ENV_STATE_KEY)


def sb3_name(name: str) -> str:
    """An observation name SB3 can use: ``"observation.image.front"`` -> ``"observation/image/front"`` (its
    extractors keep one torch module per entry, and torch module names cannot hold dots)."""
    return name.replace(".", "/")


IMAGE_PREFIX = sb3_name(flat_name(IMAGE_KEY)) + "/"


class SB3Observations(gym.ObservationWrapper):
    """The instruction as a frozen embedding Box ``[Dt]``, the privileged object state dropped, names SB3 can use
    (:func:`sb3_name`), the rest unchanged.

    The image-mode env also reports the objects' positions (``observation.environment_state``, for datasets'
    auxiliary losses); an agent meant to act from pixels must not read them, so they go unless ``privileged``.

    Args:
        env: a dust-rl env (any observation mode) whose instruction is a ``Text`` space (:class:`ConfigError`
            otherwise).
        text_encoder: the frozen text encoder; default: MiniLM, DUST's own.
        privileged: keep the object state (an oracle baseline).
    """

    def __init__(self, env: gym.Env, text_encoder: TextEncoder | None = None, privileged: bool = False) -> None:
        space = env.observation_space
        if not (isinstance(space, spaces.Dict) and isinstance(space.spaces.get(INSTRUCTION_KEY), spaces.Text)):
            entries = list(space.spaces) if isinstance(space, spaces.Dict) else type(space).__name__
            raise ConfigError(f"SB3Observations wraps a dust-rl env (gymnasium.make('DustFranka-v0', task=...)), "
                              f"whose observations hold a Text {INSTRUCTION_KEY!r}; this env's are {entries}")
        super().__init__(env)
        self.text_encoder = text_encoder or TransformersTextEncoder()
        self.dropped = set() if privileged else {ENV_STATE_NAME}
        self.observation_space = spaces.Dict({
            **{sb3_name(k): v for k, v in env.observation_space.spaces.items() if k not in self.dropped},
            sb3_name(INSTRUCTION_KEY): spaces.Box(-np.inf, np.inf, (self.text_encoder.dim,), np.float32),
        })
        self._embeddings: dict[str, np.ndarray] = {}

    def observation(self, observation: dict) -> dict:
        text = observation[INSTRUCTION_KEY]
        if text not in self._embeddings:
            with torch.no_grad():
                tokens, mask = self.text_encoder([text])
            self._embeddings[text] = pooled_text(tokens, mask)[0].numpy().astype(np.float32)
        kept = {sb3_name(k): v for k, v in observation.items() if k not in self.dropped}
        return {**kept, sb3_name(INSTRUCTION_KEY): self._embeddings[text]}


class FrozenBackboneExtractor(BaseFeaturesExtractor):
    """Camera frames through a frozen image encoder (tokens averaged per camera), other entries flattened.

    Args:
        observation_space: SB3's (channel-first once SB3 has transposed the frames).
        image_encoder: an encoder, a name (``efficientnet-lite0``, ``conv-ae``) or a file; default: DUST's.
    """

    def __init__(self, observation_space: spaces.Dict, image_encoder: ImageEncoder | str | None = None) -> None:
        # A copy each: SB3 builds several extractors from the same kwargs (actor, critic, target critic), and a
        # shared tensor would be moved by the target's soft update.
        encoder = copy.deepcopy(resolve_image_encoder(image_encoder))
        cameras = sorted(k for k in observation_space.spaces if k.startswith(IMAGE_PREFIX))
        others = sorted(k for k in observation_space.spaces if not k.startswith(IMAGE_PREFIX))
        flat = sum(int(np.prod(observation_space[k].shape)) for k in others)
        super().__init__(observation_space, features_dim=len(cameras) * encoder.dim + flat)
        # Not a submodule: PPO and A2C's orthogonal init runs ``apply`` over the extractor and would overwrite the
        # pretrained weights, and SB3 hands ``parameters()`` to the optimizer. ``_apply`` still moves it with ``to``.
        object.__setattr__(self, "encoder", encoder.requires_grad_(False).eval())
        self.cameras, self.others = cameras, others
        self.grid = encoder.native_grid()

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> FrozenBackboneExtractor:
        self.encoder._apply(fn, recurse)
        return super()._apply(fn, recurse)

    def forward(self, observations: dict[str, Tensor]) -> Tensor:
        """Features [B, C * Dv + rest]; frames arrive as SB3 gives them, floats in [0, 1], channels first."""
        with torch.no_grad():
            images = [image_tokens(self.encoder, observations[k], self.grid).mean(1) for k in self.cameras]
        rest = [observations[k].flatten(1).float() for k in self.others]
        return torch.cat([*images, *rest], dim=1)
