"""An auxiliary read-out that teaches the keypoints where the objects are, from the privileged state.

Trained through the action loss alone, keypoint heat maps learn only as
much localisation as 200 demos' action gradients ask for. Every dataset row
also stores the simulator's object positions
(``observation.environment_state``), which the policy must never read when
acting but may learn from: a small MLP predicts that state from the
keypoints' coordinates (every camera's) and the pooled instruction (which
cube is the target is named only in language), and its squared error joins
the training loss (``lambda_aux``).

Coordinates only, not the features under the keypoints: with those
(16 keypoints x 2 cameras x 112 channels) the read-out memorised the 200
training layouts by appearance. Measured on pick_place (Lite0, 3,000 steps):
training-row error ~0.5 cm, but on the first frame of a validation episode
the target cube's estimate was 7-15 cm off; trained alone on the same cached
features (lr 3e-4, batch 64; scratch runs), the coordinates-only read-out scored normalised
MSE 0.05 on 40 validation demos against 0.08 with the features.

Known limit: demonstrations hold the target cube in the gripper for most
rows, so the read-out learns "the target is where the gripper is" and is
4-14 cm off in the first steps that decide where the arm goes
(``experiments/readout_error.py``; docs/franka_results.md).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..encoders.text_encoder import pooled_text

HIDDEN = 256


class StateReadout(nn.Module):
    """Keypoint coordinates and instruction tokens to a normalised environment state [B, S].

    Args:
        n_points: P, keypoints over all cameras.
        text_dim: size of an instruction token.
        state_dim: S.
    """

    def __init__(self, n_points: int, text_dim: int, state_dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(n_points * 2 + text_dim, HIDDEN), nn.GELU(), nn.Linear(HIDDEN, state_dim))

    def forward(self, keypoints: Tensor, text_tokens: Tensor, text_mask: Tensor) -> Tensor:
        """Predicted state [B, S] from keypoints [B, P, 2 + D] (only their coordinates are read).

        The instruction enters as the mean of its real tokens.
        """
        return self.mlp(torch.cat([keypoints[..., :2].flatten(1), pooled_text(text_tokens, text_mask)], dim=-1))
