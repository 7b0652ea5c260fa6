"""The interface every frozen image encoder of the backbone implements.

DUST reads one image embedding in two places: the current frames become
condition tokens, and the frame after the chunk (t+H) becomes the vision
stream's target tokens. Both are a feature map pooled to a token grid, so an
encoder only has to turn pixels into a feature map; pooling and resizing are
shared (:func:`image_tokens`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ImageEncoder(nn.Module, ABC):
    """A pixels-to-feature-map network, used frozen.

    Attributes:
        dim: channels of the feature map (token size).
        image_size: side length the encoder expects; other sizes are resized to it.
    """

    dim: int
    image_size: int

    @abstractmethod
    def feature_map(self, images: Tensor) -> Tensor:
        """Map float images [B, 3, S, S] in [0, 1] (S = ``image_size``) to features [B, dim, h, w]."""

    @torch.no_grad()
    def native_grid(self) -> tuple[int, int]:
        """(rows, cols) of the feature map at ``image_size``: the finest token grid the encoder gives."""
        probe = torch.zeros(1, 3, self.image_size, self.image_size, device=next(self.parameters()).device)
        return tuple(self.feature_map(probe).shape[-2:])

    @abstractmethod
    def reference(self) -> dict:
        """JSON-able description that :func:`.backbone.build_image_encoder` rebuilds the module from.

        A ``"path"`` entry means the weights are read from that file or folder; without one the
        policy checkpoint stores the weights itself.
        """


def channels_first(shape: Sequence[int]) -> bool:
    """Whether camera frames of ``shape`` are ``[..., 3, H, W]`` (torchrl's layout, ``ToTensorImage``'s) rather than
    ``[..., H, W, 3]`` (gymnasium's): the layout a frame's shape, in the data or its spec, tells."""
    return shape[-3] == 3


def to_unit_float(images: Tensor, size: int) -> Tensor:
    """uint8 (or float in [0, 1]) images [B, 3, H, W] -> float [B, 3, size, size] in [0, 1]."""
    x = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    if x.shape[-2:] != (size, size):
        x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return x


def pool_tokens(features: Tensor, grid: tuple[int, int]) -> Tensor:
    """Average-pool a feature map [B, D, h, w] to a row-major token grid [B, rows*cols, D]."""
    if features.shape[-2:] != grid:
        features = F.adaptive_avg_pool2d(features, grid)
    return features.flatten(2).transpose(1, 2)


def image_tokens(encoder: ImageEncoder, images: Tensor, grid: tuple[int, int]) -> Tensor:
    """Tokens [B, rows*cols, dim] of images [B, 3, H, W] (uint8 or float in [0, 1])."""
    return pool_tokens(encoder.feature_map(to_unit_float(images, encoder.image_size)), grid)
