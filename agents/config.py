"""Configuration of the DUST agent and its baselines.

One dataclass selects the variant, the trunk size, the flow-matching loss and
the sampler, so that every baseline is the same code at the same depth/width.

Variants (paper's comparison set, docs/algorithm.md):

- ``"dust"``: dual-stream MMDiT, decoupled timesteps (per-stream AdaLN).
- ``"mmdit_shared"``: dual-stream MMDiT, one shared timestep for both streams.
- ``"decoupled"``: single stream with shared weights holding both modalities,
  per-token timestep so each modality keeps its own tau (UWM-like).
- ``"joint"``: single stream, one shared timestep (joint diffusion).
- ``"action_only"``: action flow-matching DiT without a vision stream
  (GR00T-N1.5 style).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal

Variant = Literal["dust", "mmdit_shared", "decoupled", "joint", "action_only"]
SamplerName = Literal["async", "sync", "action_only"]
KeypointSource = Literal["features", "pixels"]

VARIANTS: tuple[str, ...] = ("dust", "mmdit_shared", "decoupled", "joint", "action_only")
KEYPOINT_SOURCES: tuple[str, ...] = ("features", "pixels")

# Caps on sizes, checked before anything is allocated: a policy file names its sizes, and a file
# from elsewhere must not make loading reserve terabytes or loop over millions of blocks.
MAX_WIDTH = 8192  # any feature size (d_model, cond_dim, vision_dim, state_dim, action_dim)
MAX_HORIZON = 1024
MAX_GRID_SIDE = 64
MAX_BLOCKS = 64  # n_mmdit + n_dit
MAX_MLP_RATIO = 16.0
MAX_STEPS = 1024  # n_action_steps, vision_step_ratio
MAX_IMAGE_SIZE = 1024  # side of the frames an image encoder works at
MAX_CONV_WIDTH = 512  # channels of a convolutional encoder stage
MAX_ENCODER_LAYERS = 64  # transformer layers of an image encoder
MAX_TEXT_TOKENS = 512  # tokens per instruction
MAX_CAMERAS = 16  # cameras a policy reads
MAX_KEYPOINTS = 256  # spatial-softmax keypoints per camera
MAX_PARAMETERS = 1_000_000_000  # of the trunk, or of an image encoder: 4 GB of float32 weights
TIME_FREQ_DIM = 256  # sinusoidal features of the timestep embedding


def check_size(name: str, value: object, maximum: int, minimum: int = 1) -> None:
    """Raise ``ValueError`` unless ``value`` is an int (not a bool) in ``[minimum, maximum]``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and minimum <= value <= maximum):
        raise ValueError(f"{name} must be an int in [{minimum}, {maximum}], got {value!r}")


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
        cond_grid: (rows, cols) of the condition tokens per camera (the paper conditions on many more
            backbone tokens than it predicts); None: ``vision_grid``. The future target is the
            condition grid pooled to ``vision_grid``, so each side must be a multiple of it.
        cond_dim: feature size of the backbone condition tokens.
        keypoints: trainable spatial-softmax keypoints per camera, each one more condition token; 0: none.
        keypoint_source: what the keypoints' heat maps are computed from: ``"features"``, the frozen
            condition grid (:mod:`.keypoints`), or ``"pixels"``, a small network trained end to end on
            the raw frames (:mod:`.pixel_keypoints`; feature batches then carry ``pixels``).
        aux_state_dim: size of the privileged environment state (object positions) that the keypoints learn
            to predict during training, an auxiliary loss (:meth:`~.policy.DustPolicy.compute_loss`); the
            policy never reads it when acting. 0: no such loss. Needs ``keypoints``.
        lambda_aux: weight of that auxiliary loss.
        aux_state_input: also give the trunk that read-out's estimate, beside the robot state (the state
            token then embeds ``state_dim + aux_state_dim`` numbers): the estimated object positions reach
            the actions as the privileged-state oracle's true ones do.
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
    cond_grid: tuple[int, int] | None = None
    cond_dim: int = 384
    keypoints: int = 0
    keypoint_source: KeypointSource = "features"
    aux_state_dim: int = 0
    lambda_aux: float = 1.0
    aux_state_input: bool = False
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
        self._check_sizes()
        if self.d_model % self.n_heads:
            raise ValueError("d_model must be divisible by n_heads")
        if self.two_streams and self.n_mmdit < 2:
            raise ValueError(f"variant {self.variant!r} needs n_mmdit >= 2: MMDiT blocks alternate cross-attention "
                             f"(even) and joint attention (odd), and with n_mmdit={self.n_mmdit} the two streams "
                             "would never meet")
        if any(c % v for c, v in zip(self.condition_grid, self.vision_grid)):
            raise ValueError(f"cond_grid {self.condition_grid} must be a multiple of vision_grid {self.vision_grid}")
        if self.keypoint_source not in KEYPOINT_SOURCES:
            raise ValueError(f"unknown keypoint_source {self.keypoint_source!r}; expected one of {KEYPOINT_SOURCES}")
        if self.keypoint_source == "pixels" and not self.keypoints:
            raise ValueError("keypoint_source 'pixels' needs keypoints > 0")
        if self.aux_state_dim and not self.keypoints:
            raise ValueError("aux_state_dim needs keypoints > 0: the auxiliary loss is read off the keypoints")
        if self.aux_state_input and not self.aux_state_dim:
            raise ValueError("aux_state_input needs aux_state_dim > 0: there is no state estimate to feed")
        sampler = self.sampler_name
        if not self.has_vision and sampler != "action_only":
            raise ValueError("the action_only variant has no vision stream; use sampler='action_only'")
        if not self.decoupled and (sampler == "action_only" or self.vision_step_ratio != 1):
            raise ValueError(f"variant {self.variant!r} shares one timestep: only synchronous sampling applies")

    def _check_sizes(self) -> None:
        """Every size in range and the trunk under :data:`MAX_PARAMETERS`, before any module exists."""
        for name in ("action_dim", "state_dim", "vision_dim", "cond_dim", "d_model"):
            check_size(name, getattr(self, name), MAX_WIDTH)
        check_size("horizon", self.horizon, MAX_HORIZON)
        check_size("keypoints", self.keypoints, MAX_KEYPOINTS, minimum=0)
        check_size("aux_state_dim", self.aux_state_dim, MAX_WIDTH, minimum=0)
        check_size("n_heads", self.n_heads, self.d_model)
        check_size("n_mmdit", self.n_mmdit, MAX_BLOCKS, minimum=0)
        check_size("n_dit", self.n_dit, MAX_BLOCKS - self.n_mmdit, minimum=0)
        check_size("n_action_steps", self.n_action_steps, MAX_STEPS)
        check_size("vision_step_ratio", self.vision_step_ratio, MAX_STEPS)
        for name in ("vision_grid", "cond_grid"):
            grid = getattr(self, name)
            if grid is None and name == "cond_grid":
                continue
            if not (isinstance(grid, (tuple, list)) and len(grid) == 2):
                raise ValueError(f"{name} must be a (rows, cols) pair, got {grid!r}")
            for side in grid:
                check_size(name, side, MAX_GRID_SIDE)
        for name, low, high in (("mlp_ratio", 0.0, MAX_MLP_RATIO), ("tau_s", 0.0, 1.0), ("tau_alpha", 0.0, math.inf),
                                ("lambda_wm", None, math.inf), ("lambda_aux", None, math.inf)):
            value = getattr(self, name)
            if not (isinstance(value, numbers.Real) and math.isfinite(value)
                    and (value >= 0 if low is None else value > low) and value <= high):
                bounds = "[0, inf)" if low is None else f"({low}, {high}]"
                raise ValueError(f"{name} must be a finite number in {bounds}, got {value!r}")
        if self.n_parameters > MAX_PARAMETERS:
            raise ValueError(f"the trunk would have {self.n_parameters:.3g} parameters, more than the cap of "
                             f"{MAX_PARAMETERS:.3g}; reduce d_model, the block counts or mlp_ratio")

    @property
    def n_parameters(self) -> int:
        """Parameters of the trunk (:class:`~.dust_model.DustModel`), from the sizes alone (nothing is built)."""
        d, streams, blocks = self.d_model, 2 if self.two_streams else 1, self.n_mmdit + self.n_dit
        hidden = int(d * self.mlp_ratio)

        def linear(n_in: int, n_out: int) -> int:
            return n_in * n_out + n_out

        count = linear(self.trunk_state_dim, d) + linear(self.action_dim, d) + linear(d, self.action_dim)
        if self.has_vision:  # 3-layer MLP in, 2-layer MLP out
            count += linear(self.vision_dim, d) + 3 * linear(d, d) + linear(d, self.vision_dim)
        count += 2 * self.cond_dim + linear(self.cond_dim, d)  # LayerNorm, projection
        count += streams * (linear(TIME_FREQ_DIM, d) + linear(d, d))  # timestep embedding
        count += streams * linear(d, (6 * blocks + 2) * d)  # AdaLN modulation of all blocks and decoders
        count += blocks * streams * (4 * linear(d, d) + linear(d, hidden) + linear(hidden, d))  # attention, MLP
        return count

    @property
    def trunk_state_dim(self) -> int:
        """Numbers the state token embeds: the robot state, then the estimated object state if fed."""
        return self.state_dim + (self.aux_state_dim if self.aux_state_input else 0)

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
    def condition_grid(self) -> tuple[int, int]:
        """(rows, cols) of the condition tokens of one camera."""
        return tuple(self.cond_grid) if self.cond_grid is not None else tuple(self.vision_grid)

    @property
    def n_cond_image_tokens(self) -> int:
        """Condition tokens per camera."""
        return self.condition_grid[0] * self.condition_grid[1]

    @property
    def sampler_name(self) -> SamplerName:
        """The sampler in use: the explicit one, else async / sync / action_only by variant."""
        if self.sampler is not None:
            return self.sampler
        if not self.has_vision:
            return "action_only"
        return "async" if self.decoupled else "sync"
