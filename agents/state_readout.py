"""An auxiliary read-out that teaches the keypoints where the objects are, from the privileged state.

Trained through the action loss alone, keypoint heat maps learn only as
much localisation as 200 demos' action gradients ask for. Every dataset row
also stores the simulator's object positions
(``observation.environment_state``), which the policy must never read when
acting but may learn from: a small MLP predicts that state from the keypoints
(coordinates and attended features of every camera) and the pooled
instruction (which cube is the target is named only in language), and its
squared error joins the training loss (``lambda_aux``). At inference the
read-out is unused; only the keypoints it shaped remain.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

HIDDEN = 256


class StateReadout(nn.Module):
    """Keypoints [B, P, F] and instruction tokens to a normalised environment state [B, S].

    Args:
        n_points: P, keypoints over all cameras.
        point_dim: F, size of one keypoint feature (2 coordinates + attended features).
        text_dim: size of an instruction token.
        state_dim: S.
    """

    def __init__(self, n_points: int, point_dim: int, text_dim: int, state_dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(n_points * point_dim + text_dim, HIDDEN), nn.GELU(),
                                 nn.Linear(HIDDEN, state_dim))

    def forward(self, keypoints: Tensor, text_tokens: Tensor, text_mask: Tensor) -> Tensor:
        """Predicted state [B, S]; the instruction enters as the mean of its real tokens."""
        weights = text_mask.unsqueeze(-1).to(text_tokens.dtype)
        text = (text_tokens * weights).sum(1) / weights.sum(1).clamp_min(1.0)
        return self.mlp(torch.cat([keypoints.flatten(1), text], dim=-1))
