"""Trainable projection of frozen backbone features into the trunk's condition tokens.

Image tokens (per camera, on a grid) and instruction tokens come from
different encoders with different sizes; each source gets its own linear map
to ``cond_dim`` and a learned embedding that tells the trunk which camera and
grid cell (or that it is text) a token came from. This is the trainable
interface between the frozen backbone and the policy, like the projector
between a VLM and its action head.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

EMBED_INIT_STD = 0.02


class ConditionProjector(nn.Module):
    """Image and text features to condition tokens [B, C*N + L, cond_dim] and their mask.

    Args:
        n_cameras: C, cameras per observation.
        n_image_tokens: N, tokens per camera.
        image_dim: size of an image token.
        text_dim: size of a text token.
        cond_dim: size of a condition token.
    """

    def __init__(self, n_cameras: int, n_image_tokens: int, image_dim: int, text_dim: int, cond_dim: int) -> None:
        super().__init__()
        self.image_in = nn.Linear(image_dim, cond_dim)
        self.text_in = nn.Linear(text_dim, cond_dim)
        self.image_embed = nn.Parameter(EMBED_INIT_STD * torch.randn(n_cameras * n_image_tokens, cond_dim))
        self.text_embed = nn.Parameter(EMBED_INIT_STD * torch.randn(cond_dim))

    def forward(self, image_tokens: Tensor, text_tokens: Tensor, text_mask: Tensor) -> tuple[Tensor, Tensor]:
        """Project and concatenate.

        Args:
            image_tokens: [B, C, N, image_dim].
            text_tokens: [B, L, text_dim].
            text_mask: bool [B, L], True for real tokens.

        Returns:
            (condition tokens [B, C*N + L, cond_dim], bool mask [B, C*N + L]).
        """
        image = self.image_in(image_tokens.flatten(1, 2)) + self.image_embed
        text = self.text_in(text_tokens) + self.text_embed
        image_mask = torch.ones(image.shape[:2], dtype=torch.bool, device=image.device)
        return torch.cat([image, text], dim=1), torch.cat([image_mask, text_mask], dim=1)
