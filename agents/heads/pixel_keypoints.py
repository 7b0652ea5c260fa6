"""Keypoints learned from raw pixels, end to end: what a frozen feature map cannot place.

A 4 cm cube covers 4-5 pixels of the 128 px front camera. Frozen ImageNet
features at stride 16 keep it only as a faint change in one cell: on frames
of random resets and arm motions (objects independent of the arm) the
cube's position reads off EfficientNet-Lite0's 8x8 map no better than
chance (see :mod:`.keypoints`). The recipe robomimic and diffusion_policy
use instead is a small convolutional network trained with the policy's own
loss, random-shift augmentation, group norm (batch statistics would differ
between training and acting) and a spatial softmax on its output map.
Each camera gets its own network (stride 8: a 16x16 map at 128 px, 61k
parameters; forward and backward on 128 frames take 0.33 s on one CPU
thread); each keypoint becomes a condition token
(:class:`~..condition.ConditionProjector`), beside the frozen grid tokens.
On demonstrations alone its read-out learns the same "target = gripper"
shortcut as the frozen one (:mod:`dust_rl.train.readout.aux_frames` attacks that; docs/franka_results.md).

=============  =================  ==========================================
tensor         shape              meaning
=============  =================  ==========================================
images         [B, 3, H, W]       one camera's uint8 frames
feature map    [B, 64, H/8, W/8]  the network's output
coordinates    [B, K, 2]          expected (x, y) of each heat map, in [-1, 1]
attended       [B, K, 64]         features averaged under each heat map
=============  =================  ==========================================
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .keypoints import SpatialKeypoints

CHANNELS = 64  # of the feature map (and of each attended feature)
GROUPS = 8  # group norm groups
MAX_SHIFT = 4  # pixels of random shift while training (DrQ's 4 px at 84 px; pad by replication)


def _block(c_in: int, c_out: int, stride: int) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, 3, stride, 1), nn.GroupNorm(GROUPS, c_out), nn.ReLU()]


class PixelKeypoints(nn.Module):
    """A trainable stride-8 convolutional network and a spatial softmax on its output.

    Args:
        n_keypoints: K.
    """

    feature_dim = CHANNELS

    def __init__(self, n_keypoints: int) -> None:
        super().__init__()
        self.network = nn.Sequential(*_block(3, 16, 2), *_block(16, 32, 2), *_block(32, CHANNELS, 2),
                                     *_block(CHANNELS, CHANNELS, 1))
        self.head = SpatialKeypoints(CHANNELS, n_keypoints)

    def forward(self, images: Tensor, augment: bool = False,
                generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Coordinates [B, K, 2] and attended features [B, K, 64] of uint8 images [B, 3, H, W].

        With ``augment`` (training) each image is first shifted by up to :data:`MAX_SHIFT` pixels at
        random, drawn from ``generator``.
        """
        x = images.float() / 255.0
        if augment:
            x = random_shift(x, MAX_SHIFT, generator)
        return self.head(self.network(x))


def random_shift(images: Tensor, shift: int, generator: torch.Generator | None = None) -> Tensor:
    """Each float image [B, 3, H, W] moved by its own offset in [-shift, shift] pixels (edges replicated, as DrQ)."""
    b, _, h, w = images.shape
    padded = F.pad(images, (shift,) * 4, mode="replicate")
    dy, dx = torch.randint(0, 2 * shift + 1, (2, b), generator=generator).to(images.device)
    rows = dy[:, None] + torch.arange(h, device=images.device)  # [B, H]
    cols = dx[:, None] + torch.arange(w, device=images.device)  # [B, W]
    batch = torch.arange(b, device=images.device)[:, None, None]
    return padded.permute(0, 2, 3, 1)[batch, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)
