"""DUST as a torchrl VLA policy: frozen backbone, trainable projector and trunk, normalisation.

:class:`DustPolicy` reads torchrl's canonical VLA keys (``("observation",
"image", cam)`` uint8 ``[C, H, W]`` per camera, ``("observation", "state")``,
``language_instruction``) and writes ``("vla_action", "chunk")`` (env units)
and ``action`` (the chunk's first step). It also reads the flat gymnasium
names that a plain torchrl ``GymEnv`` keeps (``"observation.image.front"`` as
``[H, W, 3]``, or ``[3, H, W]`` behind ``ToTensorImage``;
``"observation.state"``). It is the one object users and the training,
evaluation and RL code hold (``make_policy`` and ``load_policy`` return it);
a rollout that executes ``execute_steps`` of each chunk before
re-planning runs :meth:`DustPolicy.executor`, torchrl's
:class:`~torchrl.modules.MultiStepActorWrapper` around it (see
:mod:`.execution`). Run as it is, the policy re-plans at every step.

Training runs on features, so the frozen backbone runs once per dataset row.
Feature batches (B = batch size), built by :meth:`DustPolicy.feature_batch` from
observations or from cached tokens alike, hold:

=====================  =======================  ==========================================
key                    shape                    meaning
=====================  =======================  ==========================================
``image_tokens``       [B, C, N, Dv] float      frozen tokens of each camera (``cameras`` order) on the
                                                token grid (N = ``config.n_image_tokens``: the condition
                                                grid, or the read-out's finer ``readout_grid``)
``text_tokens``        [B, L, Dt] float         frozen instruction tokens
``text_mask``          [B, L] bool              True for real instruction tokens
``state``              [B, Ds] float            normalised state
``action_chunk``       [B, H, Da] float         normalised chunk (training)
``action_is_pad``      [B, H] bool              optional; chunk entries past the episode end
``future_tokens``      [B, N_o, Dv] float       frozen tokens of ``future_camera`` at t+H, pooled to the
                                                vision grid (:meth:`DustPolicy.future_targets`; training)
``future_is_clamped``  [B] bool                 optional; t+H lies past the episode's end (no vision loss)
``pixels``             [B, C, 3, H, W] uint8    the frames themselves; only with ``keypoint_source="pixels"``
=====================  =======================  ==========================================

Image tokens arrive in the encoder's units; :meth:`DustPolicy.compute_loss`
and :meth:`DustPolicy.plan` standardise them (condition and target alike)
with the statistics in ``normalizer``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torchrl.modules.vla import VLAWrapperBase

from dust_rl.keys import (
    ACTION_KEY,
    ACTION_NOISE_KEY,
    BATCH_ACTION_CHUNK_KEY,
    BATCH_ACTION_NOISE_KEY,
    BATCH_ENV_STATE_KEY,
    BATCH_STATE_KEY,
    COND_MASK_KEY,
    COND_TOKENS_KEY,
    FUTURE_CHUNK_KEY,
    FUTURE_IS_CLAMPED_KEY,
    FUTURE_TOKENS_KEY,
    IMAGE_KEY,
    IMAGE_TOKENS_KEY,
    PIXELS_KEY,
    PREDICTED_FUTURE_KEY,
    READOUT_ESTIMATE_KEY,
    SEED_KEY,
    TEXT_MASK_KEY,
    TEXT_TOKENS_KEY,
    VISION_NOISE_KEY,
    flat_name,
)

from .condition import ConditionProjector
from .config import DustConfig, SamplerConfig
from .encoders.backbone import FrozenBackbone
from .encoders.image_encoder import channels_first, pool_tokens
from .execution import ChunkExecutor
from .heads.readout import NO_FRAME_READOUT, ObjectStateReadout, object_state_readout, squared_error
from .model.dust_model import DustModel
from .model.flow_matching import WHOLE_BATCH, Shard
from .model.precision import Precision, autocast
from .model.samplers import schedule_for
from .normalizer import Normalizer

FEATURE_KEYS = (IMAGE_TOKENS_KEY, TEXT_TOKENS_KEY, TEXT_MASK_KEY, PIXELS_KEY)


def instruction_list(value: object, n: int) -> list[str]:
    """``n`` instruction strings from a ``language_instruction`` entry (str, NonTensorData/Stack, nested lists)."""
    data = value.tolist() if hasattr(value, "tolist") else value
    if isinstance(data, str):
        return [data] * n
    flat: list[str] = []
    stack = [data]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            flat.append(item)
        else:
            stack.extend(reversed(list(item)))
    if len(flat) == 1:
        flat *= n
    if len(flat) != n:
        raise ValueError(f"got {len(flat)} instructions for a batch of {n}")
    return flat


class DustPolicy(VLAWrapperBase):
    """DUST policy (or a baseline variant) on raw observations.

    Args:
        config: trunk, loss and sampler settings; ``vision_dim`` must equal the image encoder's ``dim``.
        backbone: the frozen encoders.
        cameras: cameras read from ``("observation", "image", cam)``, in token order.
        future_camera: the camera whose t+H frame is the world-model target (default: the first).
        execute_steps: actions executed per chunk by the receding-horizon wrapper (kept with the
            checkpoint); default H // 2.

    Attributes:
        info: JSON-like provenance saved with the policy (training env id and kwargs, tasks, dataset,
            steps), so evaluation can default to the setting the policy was trained in.
    """

    def __init__(self, config: DustConfig, backbone: FrozenBackbone, cameras: Sequence[str],
                 future_camera: str | None = None, execute_steps: int | None = None) -> None:
        cameras = list(cameras)
        future_camera = cameras[0] if future_camera is None and cameras else future_camera
        if future_camera not in cameras:
            raise ValueError(f"future_camera {future_camera!r} is not among the cameras {cameras}")
        if backbone.image_dim != config.vision_dim:
            raise ValueError(f"vision_dim ({config.vision_dim}) must equal the image encoder's dim "
                             f"({backbone.image_dim})")
        execute_steps = execute_steps or max(1, config.horizon // 2)
        if not 1 <= execute_steps <= config.horizon:
            raise ValueError(f"execute_steps must be in [1, {config.horizon}], got {execute_steps}")
        self.cameras, self.writes_future = cameras, config.has_vision  # read by _update_keys in the base constructor
        super().__init__(action_dim=config.action_dim, chunk_size=config.horizon, image_key=IMAGE_KEY)
        self.future_camera, self.execute_steps = future_camera, execute_steps
        self.backbone = backbone
        self.condition = ConditionProjector(len(cameras), config.condition_grid, backbone.image_dim,
                                            backbone.text_dim, config.cond_dim, config.keypoints,
                                            config.keypoint_source, config.text_fusion)
        self.config = config  # the policy's own: set_sampler replaces it; the model reads only its model fields
        # The read-out is built before the trunk, so its initial weights do not depend on the variant: runs of one
        # seed then warm up the same read-out (dust_rl.train.readout.cache).
        self.readout: ObjectStateReadout | None = object_state_readout(
            config, len(cameras), backbone.image_dim, backbone.text_dim, self.condition.keypoints)
        if self.readout is not None:  # registered here: policy files store its weights as state_readout.*
            self.state_readout = self.readout.network
        self.model = DustModel(config)
        self.normalizer = Normalizer(config.state_dim, config.action_dim, config.vision_dim)
        self.register_buffer("action_low", torch.full((config.action_dim,), -torch.inf))
        self.register_buffer("action_high", torch.full((config.action_dim,), torch.inf))
        self.info: dict = {}
        self.precision: Precision = "fp32"
        self.mean_cameras: list[int] = []  # indices of cameras whose tokens are the mean (set_mean_cameras)

    def _update_keys(self) -> None:
        super()._update_keys()
        image = self.tensor_keys.image
        self.in_keys = [(*image, cam) for cam in self.cameras] + [k for k in self.in_keys if k != image]
        self.out_keys = [*self.out_keys, ACTION_KEY]
        if self.writes_future:
            self.out_keys += [PREDICTED_FUTURE_KEY, FUTURE_CHUNK_KEY]

    def executor(self, seeded: bool = False) -> ChunkExecutor:
        """The torchrl policy that executes ``execute_steps`` of each chunk before re-planning (for ``env.rollout``
        and collectors); ``seeded``: the sampling noise restarts from each episode's ``episode_seed`` (the env's
        :class:`~dust_rl.data.seeding.EpisodeSeedWrapper` writes it), so an episode depends on its seed only."""
        return ChunkExecutor(self, self.execute_steps, SEED_KEY if seeded else None)

    def set_action_bounds(self, low: Tensor, high: Tensor) -> None:
        """Clamp sampled actions to the env's action box."""
        self.action_low.copy_(torch.as_tensor(low, dtype=torch.float32))
        self.action_high.copy_(torch.as_tensor(high, dtype=torch.float32))

    def set_runtime(self, precision: Precision = "fp32", compile: bool = False) -> None:
        """How sampling runs here (not stored in the policy file): the trunk's precision
        (:mod:`.model.precision`) and whether its forward pass is compiled with ``torch.compile`` (every step of
        the sampler's loop then runs the compiled graph; the first call pays the compilation)."""
        self.precision = precision
        if compile:
            self.model.compile()

    def set_mean_cameras(self, cameras: Sequence[str]) -> None:
        """Replace the tokens of ``cameras`` by the training data's mean token wherever the policy reads frames (an
        ablation, not stored in the policy file: what acting loses without those views).

        Raises:
            ValueError: a camera the policy does not read.
        """
        unknown = [camera for camera in cameras if camera not in self.cameras]
        if unknown:
            raise ValueError(f"the policy reads no camera {unknown}; its cameras are {self.cameras}")
        self.mean_cameras = [self.cameras.index(camera) for camera in cameras]

    def set_sampler(self, sampler: SamplerConfig) -> None:
        """Switch between synchronous, asynchronous (N_o = q * N_A) and action-only sampling.

        Raises:
            ValueError: the sampler does not apply to the variant (e.g. async sampling of one shared timestep).
        """
        self.config = dataclasses.replace(self.config, **dataclasses.asdict(sampler))

    def trainable_parameters(self) -> list[torch.nn.Parameter]:
        """Projector and trunk parameters (the backbone is frozen)."""
        return [p for p in self.parameters() if p.requires_grad]

    def trainable_modules(self) -> nn.ModuleDict:
        """The modules training optimises and averages, by name (checkpoints key their state by these names)."""
        modules = {"condition": self.condition, "model": self.model}
        if self.readout is not None:
            modules["state_readout"] = self.readout.network
        return nn.ModuleDict(modules)

    # -- features ----------------------------------------------------------
    def canonical_view(self, td: TensorDictBase) -> TensorDictBase:
        """``td`` with the canonical keys this policy reads, taken from the flat gymnasium names where absent.

        The view nests ``"observation.state"`` and moves the channels of ``"observation.image.<cam>"``
        first, as the env side's ``make_torchrl_env`` does, unless they already are (behind torchrl's
        ``ToTensorImage``), so a plain ``GymEnv`` rollout works as is. ``td`` itself is not changed.
        """
        images = [(*self.tensor_keys.image, cam) for cam in self.cameras]
        present = td.keys(include_nested=True)
        missing = [key for key in (*images, self.tensor_keys.state) if key not in present and flat_name(key) in present]
        if not missing:
            return td
        view = td.copy()
        for key in missing:
            value = td.get(flat_name(key))
            view.set(key, value if key not in images or channels_first(value.shape) else value.movedim(-1, -3))
        return view

    @property
    def weights_device(self) -> torch.device:
        """Where the policy's weights are, after any ``policy.to(device)`` (torchrl's ``device`` attribute is
        the one given at construction)."""
        return self.normalizer.state_mean.device

    @property
    def reads_pixels(self) -> bool:
        """Whether feature batches must carry the raw frames (``pixels``) besides the frozen tokens."""
        return self.config.keypoints > 0 and self.config.keypoint_source == "pixels"

    def frames(self, td: TensorDictBase) -> Tensor:
        """Every camera's frames [*B, C, 3, H, W] from ``td`` (canonical keys, any batch shape)."""
        return torch.stack([td.get((*self.tensor_keys.image, cam)) for cam in self.cameras], dim=-4)

    def image_features(self, td: TensorDictBase) -> Tensor:
        """Frozen tokens [*B, C, N, Dv] of every camera in ``td`` (canonical keys, any batch shape)."""
        return self.frame_tokens(self.frames(td))

    def frame_tokens(self, frames: Tensor) -> Tensor:
        """Frozen tokens [*B, C, N, Dv] of frames [*B, C, 3, H, W]."""
        tokens = self.backbone.image_tokens(frames.reshape(-1, *frames.shape[-3:]), self.config.token_grid)
        return tokens.view(*frames.shape[:-3], *tokens.shape[1:])

    def future_targets(self, image_tokens: Tensor) -> Tensor:
        """World-model targets [*B, N_o, Dv]: the future camera's tokens [*B, C, N, Dv] pooled to the vision grid.

        One definition for training targets and for anything that compares a predicted future with a real one.
        """
        return self._pooled(image_tokens[..., self.cameras.index(self.future_camera), :, :],
                            tuple(self.config.vision_grid))

    def _pooled(self, tokens: Tensor, grid: tuple[int, int]) -> Tensor:
        """Tokens [*B, N, Dv] on the token grid average-pooled to ``grid`` [*B, rows * cols, Dv]."""
        if grid == self.config.token_grid:
            return tokens
        batch = tokens.shape[:-2]
        feature_map = tokens.reshape(-1, *self.config.token_grid, tokens.shape[-1]).permute(0, 3, 1, 2).float()
        pooled = pool_tokens(feature_map, grid)
        return pooled.reshape(*batch, *pooled.shape[1:])

    def observation_features(self, td: TensorDictBase) -> TensorDict:
        """Feature batch (flat [B], no training targets) of raw observations of any batch shape."""
        td = self.canonical_view(td).to(self.weights_device)
        frames = self.frames(td)
        frames = frames.reshape(-1, *frames.shape[-4:])
        image = self.frame_tokens(frames)
        if self.mean_cameras:  # an ablation (set_mean_cameras): those views say nothing
            image[:, self.mean_cameras] = self.normalizer.vision_mean.to(image.dtype)
        text, mask = self.backbone.text_tokens(instruction_list(td.get(self.tensor_keys.instruction), image.shape[0]))
        return self.feature_batch(image, text, mask, td.get(self.tensor_keys.state).reshape(image.shape[0], -1), frames)

    def feature_batch(self, image_tokens: Tensor, text_tokens: Tensor, text_mask: Tensor, state: Tensor,
                      frames: Tensor | None = None, *, action_chunk: Tensor | None = None,
                      future_image_tokens: Tensor | None = None, labels: dict | None = None) -> TensorDict:
        """The one place a feature batch (module doc) is built, for acting and for training alike.

        Args:
            image_tokens: [B, C, N, Dv] frozen tokens (from frames, or a feature cache).
            text_tokens, text_mask: the instruction's tokens and mask.
            state: [B, Ds] robot state in env units (normalised here).
            frames: [B, C, 3, H, W] uint8, kept when the keypoints read pixels.
            action_chunk: [B, H, Da] in env units (training; normalised here).
            future_image_tokens: [B, C, N, Dv] tokens at t+H (training; pooled to the world-model target here).
            labels: entries stored as they are (``action_is_pad``, ``future_is_clamped``, ``env_state``).
        """
        batch = TensorDict({IMAGE_TOKENS_KEY: image_tokens, TEXT_TOKENS_KEY: text_tokens, TEXT_MASK_KEY: text_mask,
                            BATCH_STATE_KEY: self.normalizer.normalize_state(state.float())},
                           batch_size=state.shape[:1])
        if self.reads_pixels:
            batch.set(PIXELS_KEY, frames)
        if action_chunk is not None:
            batch.set(BATCH_ACTION_CHUNK_KEY, self.normalizer.normalize_action(action_chunk))
        if future_image_tokens is not None:
            batch.set(FUTURE_TOKENS_KEY, self.future_targets(future_image_tokens))
        for key, value in (labels or {}).items():
            batch.set(key, value)
        return batch

    def _model_batch(self, features: TensorDictBase, augment: bool = False,
                     generator: torch.Generator | None = None) -> TensorDictBase:
        """The trunk's batch; ``augment`` shifts the frames of pixel keypoints at random (training only)."""
        image = self.normalizer.normalize_vision(features.get(IMAGE_TOKENS_KEY))  # on the token grid
        on_grid = self._pooled(image, self.config.condition_grid)  # what the trunk and keypoints read
        text, text_mask = features.get(TEXT_TOKENS_KEY), features.get(TEXT_MASK_KEY)
        keypoints = self._keypoints(on_grid, features, augment, generator)
        cond, mask = self.condition(on_grid, text, text_mask, keypoints)
        batch = features.exclude(*FEATURE_KEYS).set(COND_TOKENS_KEY, cond).set(COND_MASK_KEY, mask)
        # The loss and the diagnostics read the estimate, the trunk only if fed; a batch may bring the frozen
        # read-out's estimate along (dust_rl.data.features.FeatureCache.store_readout_estimates).
        if self.readout is not None and READOUT_ESTIMATE_KEY not in features.keys():
            batch.set(READOUT_ESTIMATE_KEY, self.readout.estimate(image, keypoints, text, text_mask,
                                                                  features.get(BATCH_STATE_KEY)))
        if self.config.aux_state_input:
            batch.set(BATCH_STATE_KEY, torch.cat([batch.get(BATCH_STATE_KEY), batch.get(READOUT_ESTIMATE_KEY)], dim=-1))
        if FUTURE_TOKENS_KEY in features.keys():
            future = self.standardised_future(features.get(FUTURE_TOKENS_KEY))
            if self.config.future_target == "change":
                future = (future - self._present_target(image)) / self.normalizer.future_change_scale
            batch.set(FUTURE_TOKENS_KEY, future)
        return batch

    def standardised_future(self, future_tokens: Tensor) -> Tensor:
        """Future tokens [*B, N_o, Dv] on the vision grid, in the encoder's units (a training target, or the
        ``future_tokens`` a plan returns) -> the world model's frame units (standardised after pooling).

        The units the diagnostics compare frames in."""
        return self.normalizer.standardise_future(self.normalizer.normalize_vision(future_tokens))

    def present_target(self, features: TensorDictBase) -> Tensor:
        """The present frame of a feature batch as a world-model frame [B, N_o, Dv]: "nothing moves"."""
        return self._present_target(self.normalizer.normalize_vision(features.get(IMAGE_TOKENS_KEY)))

    def _present_target(self, image: Tensor) -> Tensor:
        """:meth:`present_target` of standardised tokens [B, C, N, Dv] on the token grid."""
        return self.normalizer.standardise_future(self.future_targets(image))

    def future_changes(self, features: TensorDictBase) -> Tensor:
        """Standardised changes [B', N_o, Dv] from the present frame to t+H of a training feature batch, the
        clamped futures (t+H past the episode's end) left out: what sets a change target's unit."""
        change = self.standardised_future(features.get(FUTURE_TOKENS_KEY)) - self.present_target(features)
        return change[~features.get(FUTURE_IS_CLAMPED_KEY)] if FUTURE_IS_CLAMPED_KEY in features.keys() else change

    def _predicted_frame(self, future: Tensor, features: TensorDictBase) -> Tensor:
        """The trunk's future [B, N_o, Dv] as a standardised frame (a change target adds the present frame)."""
        if self.config.future_target == "frame":
            return future
        return self.present_target(features) + future * self.normalizer.future_change_scale

    @torch.no_grad()
    def estimate_env_state(self, features: TensorDictBase) -> Tensor:
        """The read-out's estimate [B, S] of the normalised object state for a feature batch (a diagnostic).

        Raises:
            ValueError: the policy was trained without the auxiliary state loss.
        """
        if self.readout is None:
            raise ValueError("this policy has no state read-out (trained without --model.lambda-aux)")
        image = self.normalizer.normalize_vision(features.get(IMAGE_TOKENS_KEY))  # the read-out alone, no trunk input
        keypoints = self._keypoints(self._pooled(image, self.config.condition_grid), features)
        return self.readout.estimate(image, keypoints, features.get(TEXT_TOKENS_KEY), features.get(TEXT_MASK_KEY),
                                     features.get(BATCH_STATE_KEY))

    def _keypoints(self, on_grid: Tensor, features: TensorDictBase, augment: bool = False,
                   generator: torch.Generator | None = None) -> Tensor | None:
        """The keypoint features of a feature batch (None without keypoints)."""
        if not self.config.keypoints:
            return None
        return self.condition.keypoint_features(on_grid, features.get(PIXELS_KEY, None), augment, generator)

    # -- training and inference ---------------------------------------------
    def compute_loss(self, batch: TensorDictBase, generator: torch.Generator | None = None,
                     shard: Shard = WHOLE_BATCH) -> TensorDict:
        """DUST's flow-matching loss of a feature batch (``loss``, ``loss_action``, ``loss_vision``).

        ``shard``: the batch is this part of a data-parallel batch (:class:`~.model.flow_matching.Shard`).

        In training mode the frames of pixel keypoints are shifted at random (:mod:`.heads.pixel_keypoints`).

        With a read-out and an ``env_state`` in the batch, ``loss`` also holds ``lambda_aux`` times ``loss_aux``, the
        read-out error of the privileged state (:mod:`.heads.readout`).
        """
        model_batch = self._model_batch(batch, augment=self.training, generator=generator)
        losses = self.model.compute_loss(model_batch, generator, shard)
        if self.readout is not None and BATCH_ENV_STATE_KEY in batch.keys():
            losses.set("loss_aux", squared_error(model_batch.get(READOUT_ESTIMATE_KEY), batch.get(BATCH_ENV_STATE_KEY)))
            losses.set("loss", losses.get("loss") + self.config.lambda_aux * losses.get("loss_aux"))
        return losses

    def readout_loss(self, frames: TensorDictBase, generator: torch.Generator | None = None) -> Tensor:
        """The read-out's error of the normalised object state on frames without actions (unweighted).

        Args:
            frames: ``image_tokens`` [B, C, N, Dv] (token read-out) or ``pixels`` [B, C, 3, H, W] uint8 (pixel
                keypoints; shifted at random in training mode), ``text_tokens``, ``text_mask``, ``env_state`` and the
                normalised robot ``state`` (:class:`~dust_rl.train.readout.aux_frames.AuxFrameBatches`).

        Raises:
            ValueError: the policy has no read-out that frames alone can train.
        """
        if self.readout is None or not self.readout.reads_frames:
            raise ValueError(NO_FRAME_READOUT)
        if self.readout.reads_tokens:
            image, keypoints = self.normalizer.normalize_vision(frames.get(IMAGE_TOKENS_KEY)), None
        else:
            image, keypoints = None, self.condition.keypoint_features(None, frames.get(PIXELS_KEY), self.training,
                                                                      generator)
        estimate = self.readout.estimate(image, keypoints, frames.get(TEXT_TOKENS_KEY), frames.get(TEXT_MASK_KEY),
                                         frames.get(BATCH_STATE_KEY))
        return squared_error(estimate, frames.get(BATCH_ENV_STATE_KEY))

    @torch.no_grad()
    def plan(self, td: TensorDictBase, generator: torch.Generator | None = None,
             action_noise: Tensor | None = None) -> TensorDict:
        """Sample a chunk for raw observations of any batch shape.

        Args:
            td: observations [*B].
            generator: random source of the initial noise.
            action_noise: [*B, H, Da] initial action noise in the sampler's (normalised) units, replacing the
                drawn one: the chunk is a deterministic function of it (noise-space steering; also read
                from ``ACTION_NOISE_KEY`` by :meth:`forward`).

        Returns:
            TensorDict shaped like ``td`` with ``action_chunk`` [*B, H, Da] in env units (clamped to the
            action bounds) and, with a vision stream, ``future_tokens`` [*B, N_o, Dv]: the predicted
            frozen embedding of the frame after the chunk in the encoder's units (left as noise by the
            action-only sampler).
        """
        return self.plan_features(self.observation_features(td), generator, action_noise).reshape(td.batch_size)

    @torch.no_grad()
    def plan_features(self, features: TensorDictBase, generator: torch.Generator | None = None,
                      action_noise: Tensor | None = None, vision_noise: Tensor | None = None) -> TensorDict:
        """:meth:`plan` from a flat feature batch [B] (:meth:`observation_features`), for callers that also
        read the features (an RL critic) and so encode each observation once. ``vision_noise`` [B, N_o, Dv]:
        the initial vision noise instead of the drawn one; with ``action_noise`` too, nothing is drawn and the
        chunk is a deterministic function of the two (:func:`~.model.samplers.run_schedule`)."""
        batch = self._model_batch(features)
        for key, noise in ((BATCH_ACTION_NOISE_KEY, action_noise), (VISION_NOISE_KEY, vision_noise)):
            if noise is not None:
                batch.set(key, noise.reshape(batch.batch_size[0], *noise.shape[-2:]))
        with autocast(self.weights_device, self.precision):
            out = self.model.predict_action(batch, schedule_for(self.config), generator,
                                            noise_scale=self.config.noise_scale)
        out = out.apply(lambda tensor: tensor.float() if tensor.is_floating_point() else tensor)
        if FUTURE_TOKENS_KEY in out.keys():
            out.set(FUTURE_TOKENS_KEY, self._predicted_frame(out.get(FUTURE_TOKENS_KEY), features))
        chunk = self.normalizer.denormalize_action(out.get(BATCH_ACTION_CHUNK_KEY))
        out.set(BATCH_ACTION_CHUNK_KEY, chunk.clamp(self.action_low, self.action_high))
        if FUTURE_TOKENS_KEY in out.keys():
            out.set(FUTURE_TOKENS_KEY, self.normalizer.denormalize_vision(
                self.normalizer.unstandardise_future(out.get(FUTURE_TOKENS_KEY))))
        return out

    def forward(self, tensordict: TensorDictBase, *, tensordict_out: TensorDictBase | None = None,
                **kwargs) -> TensorDictBase:
        """Write ``("vla_action", "chunk")``, ``action`` (the chunk's first step) and, with a vision stream,
        the sampled future tokens (``PREDICTED_FUTURE_KEY``, [*B, N_o, Dv] in the encoder's units).

        One joint sample gives both, so collectors and RL see the future that came with the chunk. The future
        is also written repeated along the chunk (``FUTURE_CHUNK_KEY``, [*B, H, N_o, Dv], a view), so that
        :class:`~.execution.ChunkExecutor` caches and refreshes it with the chunk and every executed step
        carries the future of its latest plan. An ``ACTION_NOISE_KEY`` entry [*B, H, Da] in ``tensordict``
        sets the initial action noise (:meth:`plan`).
        """
        planned = self.plan(tensordict, action_noise=tensordict.get(ACTION_NOISE_KEY, None))
        return self.write_plan(tensordict, planned, tensordict_out)

    def write_plan(self, tensordict: TensorDictBase, planned: TensorDictBase,
                   tensordict_out: TensorDictBase | None = None) -> TensorDictBase:
        """What :meth:`forward` writes of ``planned`` (:meth:`plan`'s output for ``tensordict``), for a caller that
        plans from features it reads too (a steering agent's policy, :class:`~dust_rl.rl.steering.SteeredPolicy`)."""
        chunk = planned.get(BATCH_ACTION_CHUNK_KEY)
        out = TensorDict({ACTION_KEY: chunk[..., 0, :]}, batch_size=chunk.shape[:-2], device=chunk.device)
        self._set_action(out, chunk=chunk)
        if self.writes_future:
            future = planned.get(FUTURE_TOKENS_KEY)
            out.set(PREDICTED_FUTURE_KEY, future)
            out.set(FUTURE_CHUNK_KEY, future.unsqueeze(-3).expand(*chunk.shape[:-1], *future.shape[-2:]))
        return self._output_tensordict(tensordict, out, tensordict_out)
