"""Pixels from a policy's world-model targets, for image encoders that cannot decode their own tokens.

DUST's vision stream predicts the future camera's frozen tokens pooled to the vision grid
(:meth:`~dust_rl.agents.DustPolicy.future_targets`: 4x4 x 40 for EfficientNet-Lite0 at stride 8). Only the conv
autoencoder has a decoder to show such a prediction as an image; for every other encoder a
:class:`TokenDecoder` is fitted afterwards on the dataset's frames (``dust-rl encoder fit-decoder``), reading
tokens exactly as the policy's targets are made, so it renders a predicted future as it renders the tokens of a
real frame. It never touches the policy: the same decoder serves every policy with the same image encoder,
future-token grid and token size. What it shows is bounded by what 16 pooled tokens keep of a frame (where the
arm and the large objects are, not millimetres); a prediction is read against the decoding of the real future's
tokens, not against the real frame.

| tensor | shape | meaning |
|---|---|---|
| tokens | [B, g*g, Dv] | future tokens on the vision grid, in the encoder's units |
| images | [B, 3, S, S] | float in [0, 1]; S = ``image_size`` |
"""

from __future__ import annotations

import pathlib
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from dust_rl.errors import CheckpointError
from dust_rl.storage.checkpoint_files import check_tensor_values, load_checkpoint, save_checkpoint

from .autoencoder import AutoencoderConfig, upsampling_decoder

TOKEN_DECODER_KIND = "dust-rl/token-decoder"
TOKEN_DECODER_FILE = "token_decoder.pt"
"""The decoder's file name beside a policy file, where ``dust-rl eval`` and ``diagnose world-model`` look for it."""


@dataclass(frozen=True)
class TokenDecoderConfig:
    """What a :class:`TokenDecoder` reads and draws.

    Attributes:
        encoder: the image encoder's reference (``ImageEncoder.reference()``) whose tokens it reads.
        grid: side of the future-token grid (the policy's ``vision_grid``).
        dim: token size Dv.
        image_size: side of the images drawn; ``grid`` times a power of 2.
        width: channels of the last (highest-resolution) stage; doubled per stage up to ``max_width``.
        max_width: cap on stage channels.
    """

    encoder: dict
    grid: int
    dim: int
    image_size: int = 64
    width: int = 16
    max_width: int = 128

    def stage_channels(self) -> list[int]:
        """Channels per stage, highest resolution first (as the conv autoencoder's mirrored encoder)."""
        return AutoencoderConfig(self.image_size, self.grid, self.dim, self.width, self.max_width).stage_channels()


class TokenDecoder(nn.Module):
    """Future tokens [B, g*g, Dv] -> images [B, 3, S, S]; tokens standardised per channel with statistics of
    the frames it was fitted on (:meth:`set_token_stats`)."""

    def __init__(self, config: TokenDecoderConfig) -> None:
        super().__init__()
        self.config = config
        self.decoder = upsampling_decoder(config.dim, config.stage_channels())
        self.register_buffer("token_mean", torch.zeros(config.dim))
        self.register_buffer("token_std", torch.ones(config.dim))

    def forward(self, tokens: Tensor) -> Tensor:
        grid = self.config.grid
        if tokens.shape[-2:] != (grid * grid, self.config.dim):
            raise ValueError(f"tokens must be [B, {grid * grid}, {self.config.dim}], got {list(tokens.shape)}")
        standard = (tokens.float() - self.token_mean) / self.token_std
        return self.decoder(standard.transpose(1, 2).reshape(tokens.shape[0], self.config.dim, grid, grid))

    @torch.no_grad()
    def set_token_stats(self, mean: Tensor, std: Tensor) -> None:
        self.token_mean.copy_(mean)
        self.token_std.copy_(std.clamp_min(1e-6))

    def check_reads(self, encoder: dict, grid: tuple[int, int], dim: int, source: str | pathlib.Path) -> None:
        """Raise :class:`CheckpointError` unless this decoder reads ``encoder``'s tokens of size ``dim`` on ``grid``."""
        mine = (self.config.encoder, (self.config.grid, self.config.grid), self.config.dim)
        if mine != (encoder, tuple(grid), dim):
            raise CheckpointError(f"{source}: the decoder reads {mine[1][0]}x{mine[1][1]} x {mine[2]} tokens of "
                                  f"{mine[0]}, the policy predicts {grid[0]}x{grid[1]} x {dim} of {encoder}: fit one "
                                  "for this policy (dust-rl encoder fit-decoder)")


def save_token_decoder(decoder: TokenDecoder, path: str | pathlib.Path, info: dict | None = None) -> pathlib.Path:
    """Write ``decoder`` atomically to one file; ``info``: JSON-able provenance (data, losses, command)."""
    return save_checkpoint({"config": asdict(decoder.config), "state_dict": decoder.state_dict(),
                            "info": info or {}}, path, TOKEN_DECODER_KIND)


def load_token_decoder(path: str | pathlib.Path) -> TokenDecoder:
    """Read a decoder written by :func:`save_token_decoder` (raises :class:`CheckpointError` if unusable)."""
    payload = load_checkpoint(path, TOKEN_DECODER_KIND)
    try:
        decoder = TokenDecoder(TokenDecoderConfig(**payload["config"]))
        state = payload["state_dict"]
        check_tensor_values(state, decoder.state_dict())
        decoder.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: token decoder does not load ({err})") from err
    return decoder.eval().requires_grad_(False)
