"""Small convolutional autoencoder: the default frozen image encoder.

No pretrained image weights can be downloaded here, so the project trains
this on its own environment frames (``dust-rl pretrain-encoder``) and freezes
it. An autoencoder rather than a contrastive model because its decoder can
render the future tokens DUST predicts back to pixels.

The latent is a ``latent_grid x latent_grid`` map of ``dim`` channels, the
same grid the vision stream predicts (4x4 tokens of 64 by default), so the
decoder renders predicted futures exactly as it renders encoded frames.
Latents are standardised per channel with statistics of the training frames
(:meth:`ConvAutoencoder.set_latent_stats`), which gives flow matching targets
of roughly unit scale.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from .image_encoder import ImageEncoder


@dataclass(frozen=True)
class AutoencoderConfig:
    """Shape of a `ConvAutoencoder`.

    Attributes:
        image_size: input/output side length; must be `latent_grid` times a power of 2.
        latent_grid: side of the latent token grid.
        dim: latent channels (token size).
        width: channels of the first (highest-resolution) stage; doubled per stage.
        max_width: cap on stage channels.
    """

    image_size: int = 128
    latent_grid: int = 4
    dim: int = 64
    width: int = 16
    max_width: int = 128

    @property
    def n_stages(self) -> int:
        """Stride-2 stages from image to latent."""
        ratio = self.image_size // self.latent_grid
        if ratio < 2 or ratio * self.latent_grid != self.image_size or ratio & (ratio - 1):
            raise ValueError(f"image_size ({self.image_size}) must be latent_grid ({self.latent_grid}) "
                             "times a power of 2")
        return int(math.log2(ratio))

    def stage_channels(self) -> list[int]:
        """Channels after each encoder stage, highest resolution first."""
        return [min(self.width * 2**i, self.max_width) for i in range(self.n_stages)]


def conv_norm_act(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1), nn.GroupNorm(min(8, c_out), c_out), nn.SiLU())


def upsampling_decoder(dim: int, channels: list[int]) -> nn.Sequential:
    """Latent map [B, dim, g, g] -> images [B, 3, g * 2**n, g * 2**n] in [0, 1]: the encoder's stages (``channels``,
    highest resolution first) mirrored, nearest-neighbour upsampling between them."""
    up = nn.Upsample(scale_factor=2, mode="nearest")
    layers: list[nn.Module] = [conv_norm_act(dim, channels[-1])]
    for c_in, c_out in zip(channels[::-1], channels[-2::-1]):
        layers += [up, conv_norm_act(c_in, c_out)]
    return nn.Sequential(*layers, up, nn.Conv2d(channels[0], 3, 3, 1, 1), nn.Sigmoid())


class ConvAutoencoder(ImageEncoder):
    """Strided-conv encoder to a token grid and an upsampling decoder back to pixels.

    Args:
        config: sizes.
    """

    def __init__(self, config: AutoencoderConfig = AutoencoderConfig()) -> None:
        super().__init__()
        self.config = config
        self.dim, self.image_size = config.dim, config.image_size
        channels = config.stage_channels()
        encoder = [conv_norm_act(c_in, c_out, stride=2) for c_in, c_out in zip([3, *channels], channels)]
        self.encoder = nn.Sequential(*encoder, nn.Conv2d(channels[-1], config.dim, 3, 1, 1))
        self.decoder = upsampling_decoder(config.dim, channels)
        self.register_buffer("latent_mean", torch.zeros(config.dim))
        self.register_buffer("latent_std", torch.ones(config.dim))

    def raw_latent(self, images: Tensor) -> Tensor:
        """Unstandardised latent [B, dim, g, g] of float images [B, 3, S, S] in [0, 1]."""
        return self.encoder(images)

    def feature_map(self, images: Tensor) -> Tensor:
        """Standardised latent [B, dim, g, g]."""
        return (self.raw_latent(images) - self.latent_mean[:, None, None]) / self.latent_std[:, None, None]

    def decode(self, latent: Tensor) -> Tensor:
        """Images [B, 3, S, S] in [0, 1] from standardised latents, as a map [B, dim, g, g] or tokens [B, g*g, dim]."""
        if latent.dim() == 3:
            g = self.config.latent_grid
            latent = latent.transpose(1, 2).reshape(latent.shape[0], self.dim, g, g)
        return self.decoder(latent * self.latent_std[:, None, None] + self.latent_mean[:, None, None])

    def reconstruction_loss(self, images: Tensor) -> Tensor:
        """Pixel MSE of encoding then decoding float images [B, 3, S, S] in [0, 1]."""
        return (self.decoder(self.raw_latent(images)) - images).square().mean()

    @torch.no_grad()
    def set_latent_stats(self, mean: Tensor, std: Tensor) -> None:
        """Set the per-channel statistics that standardise the latent (from the training frames)."""
        self.latent_mean.copy_(mean)
        self.latent_std.copy_(std.clamp_min(1e-6))

    def reference(self) -> dict:
        return {"kind": "conv_autoencoder", "config": asdict(self.config)}
