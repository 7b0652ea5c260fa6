"""Configuration of the DUST agent and its baselines.

One dataclass selects the variant, the trunk size, the flow-matching loss and
the sampler, so that every baseline is the same code at the same depth/width.

Variants (paper's comparison set, DESIGN §3):

- ``"dust"``: dual-stream MMDiT, decoupled timesteps (per-stream AdaLN).
- ``"mmdit_shared"``: dual-stream MMDiT, one shared timestep for both streams.
- ``"decoupled"``: single stream with shared weights holding both modalities,
  per-token timestep so each modality keeps its own tau (UWM-like).
- ``"joint"``: single stream, one shared timestep (joint diffusion).
- ``"action_only"``: action flow-matching DiT without a vision stream
  (GR00T-N1.5 style).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Variant = Literal["dust", "mmdit_shared", "decoupled", "joint", "action_only"]
SamplerName = Literal["async", "sync", "action_only"]

VARIANTS: tuple[str, ...] = ("dust", "mmdit_shared", "decoupled", "joint", "action_only")


@dataclass(frozen=True)
class DustConfig:
    """Sizes, variant and sampling settings of a DUST agent.

    Attributes:
        variant: which model of the comparison set to build (see module doc).
        action_dim: size of one action vector.
        horizon: action chunk length H.
        state_dim: size of the (normalised) proprioceptive state vector.
        vision_dim: feature size of one future-vision token.
        vision_grid: (rows, cols) of the future-vision token grid; N_o = rows*cols.
        cond_dim: feature size of the backbone condition tokens.
        d_model: trunk width.
        n_heads: attention heads.
        n_mmdit: dual-stream MMDiT blocks (single-stream variants use the same count of shared blocks).
        n_dit: per-stream DiT blocks after the MMDiT blocks.
        mlp_ratio: MLP hidden size over d_model.
        lambda_wm: weight of the vision (world-model) loss.
        tau_s: GR00T's s in tau = (s - u) / s.
        tau_alpha: alpha of u ~ Beta(alpha, 1).
        sampler: ``"async"``, ``"sync"`` or ``"action_only"``; None picks the variant's natural one.
        n_action_steps: N_A, action denoising steps per chunk.
        vision_step_ratio: q, so that the vision stream takes N_o = q * N_A steps (async only).
    """

    variant: Variant = "dust"
    action_dim: int = 7
    horizon: int = 16
    state_dim: int = 8
    vision_dim: int = 64
    vision_grid: tuple[int, int] = (4, 4)
    cond_dim: int = 384
    d_model: int = 128
    n_heads: int = 4
    n_mmdit: int = 4
    n_dit: int = 2
    mlp_ratio: float = 4.0
    lambda_wm: float = 1.0
    tau_s: float = 0.999
    tau_alpha: float = 1.5
    sampler: SamplerName | None = None
    n_action_steps: int = 4
    vision_step_ratio: int = 1

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {VARIANTS}")
        if self.d_model % self.n_heads:
            raise ValueError("d_model must be divisible by n_heads")
        if self.n_action_steps < 1 or self.vision_step_ratio < 1:
            raise ValueError("n_action_steps and vision_step_ratio must be >= 1")
        sampler = self.sampler_name
        if not self.has_vision and sampler != "action_only":
            raise ValueError("the action_only variant has no vision stream; use sampler='action_only'")
        if not self.decoupled and (sampler == "action_only" or self.vision_step_ratio != 1):
            raise ValueError(f"variant {self.variant!r} shares one timestep: only synchronous sampling applies")

    @property
    def two_streams(self) -> bool:
        """Whether actions and vision keep separate weights (MMDiT)."""
        return self.variant in ("dust", "mmdit_shared")

    @property
    def decoupled(self) -> bool:
        """Whether each modality has its own timestep."""
        return self.variant in ("dust", "decoupled", "action_only")

    @property
    def has_vision(self) -> bool:
        """Whether the model predicts future-vision tokens."""
        return self.variant != "action_only"

    @property
    def n_vision_tokens(self) -> int:
        """N_o, the number of future-vision tokens."""
        return self.vision_grid[0] * self.vision_grid[1]

    @property
    def sampler_name(self) -> SamplerName:
        """The sampler in use: the explicit one, else async / sync / action_only by variant."""
        if self.sampler is not None:
            return self.sampler
        if not self.has_vision:
            return "action_only"
        return "async" if self.decoupled else "sync"
