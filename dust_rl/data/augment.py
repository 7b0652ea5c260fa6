"""Image augmentation for training on cached frozen features.

Features are cached once per frame, so augmenting frames on the fly would
mean re-running the frozen encoder every step. Instead the cache keeps K
views of every frame: view 0 is the frame itself, views 1..K-1 are random
shifts (replicate padding then a random crop, as DrQ does) with mild
brightness/contrast/saturation jitter, drawn from a generator seeded by the
first row of the encoded batch and the view, so a cache is the same on every
rebuild.
Training samples a view per window; the world-model target always uses view 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dust_rl.agents.heads.pixel_keypoints import random_shift

MAX_SHIFT = 6  # pixels at 128 px (about 5% of the frame, as in DrQ's 4 px at 84 px)
JITTER = 0.15  # brightness, contrast and saturation factors drawn from [1 - JITTER, 1 + JITTER]


def view_generator(first_row: int, view: int) -> torch.Generator:
    """The random source of one augmented view of the batch of rows starting at ``first_row``."""
    return torch.Generator().manual_seed(1_000_003 * view + first_row)


def augment_frames(frames: Tensor, generator: torch.Generator) -> Tensor:
    """A random shift and colour jitter of uint8 frames [N, 3, H, W] (one draw per frame), uint8 out."""
    n = frames.shape[0]
    x = random_shift(frames.float() / 255.0, MAX_SHIFT, generator)
    factors = 1 + JITTER * (2 * torch.rand(3, n, 1, 1, 1, generator=generator) - 1)
    brightness, contrast, saturation = factors
    x = x * brightness
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * contrast + mean
    grey = x.mean(dim=1, keepdim=True)
    x = (x - grey) * saturation + grey
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)
