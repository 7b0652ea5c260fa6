"""Trainable projection of frozen backbone features into the trunk's condition tokens.

Image tokens (per camera, on a grid) and instruction tokens come from
different encoders with different sizes; each source gets its own linear map
to ``cond_dim`` and a learned embedding that tells the trunk which camera and
grid cell (or that it is text) a token came from. This is the trainable
interface between the frozen backbone and the policy, like the projector
between a VLM and its action head. With ``n_keypoints`` > 0 each camera also
gets trainable spatial-softmax keypoints that become tokens of their own:
coordinates finer than the grid, for grasping. Their heat maps come from the
frozen grid (:mod:`.heads.keypoints`) or from the raw frames through a small
network trained with the policy (:mod:`.heads.pixel_keypoints`).

With ``text_fusion`` the image tokens also see the instruction before the
trunk does: the pooled instruction is added to every image token and a
residual MLP (hidden width ``FUSION_HIDDEN``) mixes the two per token, the
structure of the attention probe (:mod:`dust_rl.agents.heads.attention_pooling`) that reads
the expert's first move off the frozen stride-8 tokens to 1.2 cm. In the
policy it did not help the trunk learn that move (docs/franka_results.md, pick_place).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .config import KeypointSource
from .encoders.text_encoder import pooled_text
from .heads.keypoints import SpatialKeypoints
from .heads.pixel_keypoints import PixelKeypoints

EMBED_INIT_STD = 0.02
FUSION_HIDDEN = 128


class ConditionProjector(nn.Module):
    """Image and text features to condition tokens [B, C*(N + K) + L, cond_dim] and their mask.

    Args:
        n_cameras: C, cameras per observation.
        grid: (rows, cols) of each camera's tokens; N = rows * cols.
        image_dim: size of an image token.
        text_dim: size of a text token.
        cond_dim: size of a condition token.
        n_keypoints: K, spatial-softmax keypoints per camera (0: none).
        keypoint_source: ``"features"`` (heat maps on the image tokens) or ``"pixels"`` (on the raw frames).
        text_fusion: condition each image token on the pooled instruction (module doc).
    """

    def __init__(self, n_cameras: int, grid: tuple[int, int], image_dim: int, text_dim: int, cond_dim: int,
                 n_keypoints: int = 0, keypoint_source: KeypointSource = "features", text_fusion: bool = False) -> None:
        super().__init__()
        self.grid = tuple(grid)
        self.image_in = nn.Linear(image_dim, cond_dim)
        self.text_in = nn.Linear(text_dim, cond_dim)
        self.image_embed = nn.Parameter(EMBED_INIT_STD * torch.randn(n_cameras * grid[0] * grid[1], cond_dim))
        self.text_embed = nn.Parameter(EMBED_INIT_STD * torch.randn(cond_dim))
        self.from_pixels = keypoint_source == "pixels"
        heads = [PixelKeypoints(n_keypoints) if self.from_pixels else SpatialKeypoints(image_dim, n_keypoints)
                 for _ in range(n_cameras if n_keypoints else 0)]
        self.keypoints = nn.ModuleList(heads)
        if n_keypoints:
            attended_dim = PixelKeypoints.feature_dim if self.from_pixels else image_dim
            self.keypoint_in = nn.Linear(2 + attended_dim, cond_dim)
            self.keypoint_embed = nn.Parameter(EMBED_INIT_STD * torch.randn(n_cameras * n_keypoints, cond_dim))
        self.fusion = None
        if text_fusion:
            self.fusion_text_in = nn.Linear(text_dim, cond_dim)
            self.fusion = nn.Sequential(nn.LayerNorm(cond_dim), nn.Linear(cond_dim, FUSION_HIDDEN), nn.GELU(),
                                        nn.Linear(FUSION_HIDDEN, cond_dim))

    def keypoint_features(self, image_tokens: Tensor | None, pixels: Tensor | None = None, augment: bool = False,
                          generator: torch.Generator | None = None) -> Tensor:
        """Per camera and keypoint, its coordinates and attended features [B, C*K, 2 + attended size].

        Args:
            image_tokens: [B, C, N, image_dim], row-major on ``grid``; needs ``n_keypoints`` > 0 (unread, and
                may be None, with ``keypoint_source="pixels"``).
            pixels: uint8 frames [B, C, 3, H, W]; needed (and only read) with ``keypoint_source="pixels"``.
            augment: shift those frames at random (drawn from ``generator``), as in training.
        """
        if not self.from_pixels:
            maps = image_tokens.transpose(-1, -2).unflatten(-1, self.grid)  # [B, C, D, rows, cols]
            return torch.cat([torch.cat(head(maps[:, c]), dim=-1) for c, head in enumerate(self.keypoints)], dim=1)
        if pixels is None:
            raise ValueError("pixel keypoints need the raw frames: the feature batch has no 'pixels'")
        return torch.cat([torch.cat(head(pixels[:, c], augment, generator), dim=-1)
                          for c, head in enumerate(self.keypoints)], dim=1)

    def forward(self, image_tokens: Tensor, text_tokens: Tensor, text_mask: Tensor,
                keypoints: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Project and concatenate.

        Args:
            image_tokens: [B, C, N, image_dim], row-major on ``grid``.
            text_tokens: [B, L, text_dim].
            text_mask: bool [B, L], True for real tokens.
            keypoints: :meth:`keypoint_features` if already computed (None: computed here when used).

        Returns:
            (condition tokens [B, C*(N + K) + L, cond_dim], bool mask of the same length).
        """
        image = [self.image_in(image_tokens.flatten(1, 2)) + self.image_embed]
        if self.fusion is not None:
            named = self.fusion_text_in(pooled_text(text_tokens, text_mask))[:, None]
            image[0] = image[0] + self.fusion(image[0] + named)
        if self.keypoints:
            keypoints = self.keypoint_features(image_tokens) if keypoints is None else keypoints
            image.append(self.keypoint_in(keypoints) + self.keypoint_embed)
        image = torch.cat(image, dim=1)
        text = self.text_in(text_tokens) + self.text_embed
        image_mask = torch.ones(image.shape[:2], dtype=torch.bool, device=image.device)
        return torch.cat([image, text], dim=1), torch.cat([image_mask, text_mask], dim=1)
