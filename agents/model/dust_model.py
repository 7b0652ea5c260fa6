"""The DUST trunk and its baselines as one configurable module.

Token layout: the action modality is [state token, H action tokens], the
vision modality is N_o future-vision tokens. Two-stream variants keep them as
two streams with separate weights, meeting only in the joint attention of the
MMDiT blocks; the streams are stacked as [2, B, N, d], the shorter one
zero-padded to the longer (padding is masked out of every attention and never
decoded), so that both run through each layer in one batched matmul.
Single-stream variants concatenate the modalities into one stream with shared
weights ([1, B, 1 + H + N_o, d]); the action-only variant has no vision tokens.

Blocks: ``n_mmdit`` blocks whose self-attention is joint across streams, then
``n_dit`` blocks whose self-attention stays within each stream; cross-attention
to the backbone tokens alternates with self-attention (see :mod:`.mmdit`).
Condition tokens are normalised and projected to ``d_model`` once, shared by
all cross-attention blocks (cheaper than per-block projections from a wide
backbone).

Timesteps reach the blocks only through AdaLN. Each stream of a two-stream
model has its own timestep embedder and modulation weights, fed by its own
tau only; the single-stream ``"decoupled"`` variant gives every token the
modulation of its own modality's tau.

Besides the velocity network, the model holds DUST's decoupled
flow-matching loss (:meth:`DustModel.compute_loss`) and chunk sampling
(:meth:`DustModel.predict_action`, the sampler schedule given at call time)
on encoded, normalised inputs; the frozen backbone and the torchrl policy
live in :mod:`..policy`. Names follow diffusion_policy.

TensorDict keys (B = batch size):

=====================  ===================  =====================================================
key                    shape / dtype        meaning
=====================  ===================  =====================================================
``cond_tokens``        [B, Nc, Dc] float    backbone condition tokens (image + language)
``cond_mask``          [B, Nc] bool         optional; True where a condition token is valid
``state``              [B, Ds] float        normalised proprioceptive state
``action_chunk``       [B, H, Da] float     normalised action chunk (training; output of predict)
``action_is_pad``      [B, H] bool          optional; True for entries past the episode end
``has_action``         [B] bool             optional; False for action-free (video-only) samples
``future_tokens``      [B, N_o, Dv] float   frozen embedding of the frame after the chunk (t+H);
                                            training target, and predicted by ``predict_action``
``future_is_clamped``  [B] bool             optional; True where t+H lies past the episode's last
                                            stored row, so ``future_tokens`` hold that row instead
                                            (read by the diagnostics; the loss treats it as the future)
=====================  ===================  =====================================================

``action_is_pad`` entries and action-free samples are left out of the action
loss. A window whose t+H lies past the episode's end has its episode's last
frame as its future (``future_is_clamped``): an episode ends where its task is
done, and the scene then holds still. That frame is the world model's target
as it is the action stream's input, one rule for both streams. Before, it was
fed to the actions but left out of the vision loss, so the actions learnt from
a frame the world model was never taught to predict (on press_button a
quarter to a third of the training windows). Feeding the actions pure noise
there instead (tau_o = 0, as an action-free sample's actions) was measured and
not kept: the main job's held-out success fell from 98% to 90% (0 episodes
gained, 4 lost against the same code without it; docs/results/2026-12-02-speed-and-perception.md).

An action-free sample also gets pure-noise action tokens (tau_A = 0 in
the decoupled variants, as UWM does), so the vision stream learns the future
marginalised over actions, and the sampler's first steps (tau_A = 0) see the
same input distribution.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import Tensor, nn

from dust_rl.keys import (
    ACTION_IS_PAD_KEY,
    BATCH_ACTION_CHUNK_KEY,
    BATCH_ACTION_NOISE_KEY,
    BATCH_STATE_KEY,
    COND_MASK_KEY,
    COND_TOKENS_KEY,
    FUTURE_TOKENS_KEY,
    HAS_ACTION_KEY,
    VISION_NOISE_KEY,
)

from ..config import DustConfig
from .adaln import Modulation
from .embeddings import TimestepEmbedder, TokenDecoder, TokenEncoder, sincos_positions_1d, sincos_positions_2d
from .flow_matching import (
    WHOLE_BATCH,
    Shard,
    action_validity,
    cpu_drawn,
    decoupled_loss,
    interpolate,
    sample_tau,
    velocity_target,
)
from .mmdit import KV, AttentionKind, Block
from .samplers import DenoiseStep, VisionSource, run_schedule

MODS_PER_BLOCK = 6  # shift, scale, gate for attention, then for the MLP
ACTION_STREAM, VISION_STREAM = 0, 1  # rows of the stacked streams of a two-stream model
ALL_STREAMS = slice(None)
SCALE_SLOTS = (1, 4)


@dataclass
class ChunkContext:
    """What stays fixed while one action chunk is denoised.

    Attributes:
        state_token: embedded state [B, 1, d].
        cross_kv: per block, the per-stream condition K/V (None for self-attention blocks).
        cond_mask: bool [B, Nc] (True = valid) or None when all tokens are valid.
    """

    state_token: Tensor
    cross_kv: list[KV | None]
    cond_mask: Tensor | None

    @property
    def batch_size(self) -> int:
        """Number of chunks being denoised."""
        return self.state_token.shape[0]


def pad_tokens(x: Tensor, n: int) -> Tensor:
    """Zero-pad tokens [B, N, d] to n tokens."""
    return x if x.shape[1] == n else F.pad(x, (0, 0, 0, n - x.shape[1]))


class DustModel(nn.Module):
    """Velocity network for actions and future-vision tokens.

    Args:
        config: sizes and variant.
    """

    def __init__(self, config: DustConfig) -> None:
        super().__init__()
        self.config = config
        d = config.d_model
        self.n_streams = 2 if config.two_streams else 1
        n_blocks = config.n_mmdit + config.n_dit
        self.n_action_tokens = 1 + config.horizon  # state token first
        n_vision = config.n_vision_tokens if config.has_vision else 0

        self.state_in = nn.Linear(config.trunk_state_dim, d)
        self.action_in = TokenEncoder([config.action_dim, d], sincos_positions_1d(config.horizon, d))
        self.action_out = TokenDecoder([d, config.action_dim])
        if config.has_vision:
            self.vision_in = TokenEncoder([config.vision_dim, d, d, d], sincos_positions_2d(*config.vision_grid, d))
            self.vision_out = TokenDecoder([d, d, config.vision_dim])
        self.cond_in = nn.Sequential(nn.LayerNorm(config.cond_dim), nn.Linear(config.cond_dim, d))
        self.time_embed = TimestepEmbedder(self.n_streams, d)
        # Per stream: 6 vectors per block, then the shift and scale of its decoder(s) (shared by both
        # modality decoders in single-stream variants, like every other trunk weight there).
        scale_slots = [MODS_PER_BLOCK * i + s for i in range(n_blocks) for s in SCALE_SLOTS]
        n_slots = MODS_PER_BLOCK * n_blocks + 2
        self.modulation = Modulation(self.n_streams, d, n_slots, [*scale_slots, n_slots - 1])
        kinds = [self._block_kind(i) for i in range(n_blocks)]
        self.blocks = nn.ModuleList(Block(k, self.n_streams, d, config.n_heads, config.mlp_ratio) for k in kinds)
        # After the last joint block the streams no longer interact: one whose output is not needed can go.
        self.last_joint_block = max((i for i, k in enumerate(kinds) if k == "joint"), default=-1)

        key_valid = token_modality = None
        if config.two_streams:  # streams are padded to a common token count; padding is never attended to
            self.n_tokens = max(self.n_action_tokens, n_vision)
            if self.n_action_tokens != n_vision:
                key_valid = torch.arange(self.n_tokens) < torch.tensor([[self.n_action_tokens], [n_vision]])
        elif config.has_vision and config.decoupled:
            token_modality = torch.tensor([0] * self.n_action_tokens + [1] * n_vision)
        self.register_buffer("key_valid", key_valid, persistent=False)
        self.register_buffer("token_modality", token_modality, persistent=False)

    def _block_kind(self, index: int) -> AttentionKind:
        if index % 2 == 0:
            return "cross"
        return "joint" if self.config.two_streams and index < self.config.n_mmdit else "self"

    def encode_context(self, state: Tensor, cond_tokens: Tensor, cond_mask: Tensor | None = None) -> ChunkContext:
        """Embed what the denoising steps of one chunk share.

        Args:
            state: normalised state [B, Ds].
            cond_tokens: backbone tokens [B, Nc, Dc].
            cond_mask: bool [B, Nc], True where a token is valid; None if all are.
        """
        cond = self.cond_in(cond_tokens)
        return ChunkContext(
            state_token=self.state_in(state).unsqueeze(1),
            cross_kv=[block.condition_kv(cond) for block in self.blocks],
            cond_mask=cond_mask,
        )

    def _stream_taus(self, tau_a: Tensor, tau_o: Tensor | None) -> Tensor:
        """Flow times [S, B, T] seen by each stream: T = 2 (action, vision) for the single-stream decoupled variant."""
        cfg = self.config
        if tau_o is not None and not cfg.decoupled and not torch.equal(tau_a, tau_o):
            raise ValueError(f"variant {cfg.variant!r} shares one timestep; got tau_a != tau_o")
        if cfg.two_streams:
            return torch.stack([tau_a, tau_o]).unsqueeze(-1)
        if self.token_modality is not None:
            return torch.stack([tau_a, tau_o], dim=-1).unsqueeze(0)
        return tau_a.view(1, -1, 1)

    def _tokens(self, ctx: ChunkContext, noisy_action: Tensor, noisy_vision: Tensor | None) -> Tensor:
        """Embedded tokens [S, B, N, d]."""
        x_a = torch.cat([ctx.state_token, self.action_in(noisy_action)], dim=1)
        if noisy_vision is None:
            return x_a.unsqueeze(0)
        x_o = self.vision_in(noisy_vision)
        if self.config.two_streams:
            return torch.stack([pad_tokens(x_a, self.n_tokens), pad_tokens(x_o, self.n_tokens)])
        return torch.cat([x_a, x_o], dim=1).unsqueeze(0)

    def forward(
        self,
        ctx: ChunkContext,
        noisy_action: Tensor,
        noisy_vision: Tensor | None,
        tau_a: Tensor,
        tau_o: Tensor | None,
        need_action: bool = True,
        need_vision: bool = True,
    ) -> tuple[Tensor | None, Tensor | None]:
        """Predict velocities of both modalities.

        Args:
            ctx: output of :meth:`encode_context`.
            noisy_action: A_tau [B, H, Da].
            noisy_vision: o_tau [B, N_o, Dv]; None for the action-only variant.
            tau_a: action flow time [B].
            tau_o: vision flow time [B]; None for the action-only variant. Shared-timestep
                variants require it to equal ``tau_a``.
            need_action: compute the action velocity (a sampler step that keeps actions fixed may skip it).
            need_vision: compute the vision velocity.

        Returns:
            (action velocity [B, H, Da], vision velocity [B, N_o, Dv]); None where not needed or no vision.
        """
        need_vision = need_vision and noisy_vision is not None
        mods = self.modulation(F.silu(self.time_embed(self._stream_taus(tau_a, tau_o))), self.token_modality)
        x, streams = self._run_blocks(self._tokens(ctx, noisy_action, noisy_vision), mods, ctx,
                                      self._needed_streams(need_action, need_vision))
        shift, scale = mods[-2], mods[-1]  # the decoders' AdaLN vectors
        if self.n_streams == 2:
            return self._decode_streams(x, streams, shift, scale, need_action, need_vision)
        return self._decode_single_stream(x, shift, scale, need_action, need_vision)

    def _needed_streams(self, need_action: bool, need_vision: bool) -> slice:
        """The streams whose output is needed: only those run past the last joint block (two streams)."""
        if self.n_streams == 1:
            return ALL_STREAMS
        first = ACTION_STREAM if need_action else VISION_STREAM
        return slice(first, (VISION_STREAM if need_vision else ACTION_STREAM) + 1)

    def _run_blocks(self, x: Tensor, mods: list[Tensor], ctx: ChunkContext, needed: slice) -> tuple[Tensor, slice]:
        """Tokens [S', B, N, d] after every block, and which streams S' they are (``needed`` after the last joint
        block: a stream nothing reads any more is dropped there)."""
        streams = ALL_STREAMS
        for i, (block, kv) in enumerate(zip(self.blocks, ctx.cross_kv)):
            if i == self.last_joint_block + 1 and needed != ALL_STREAMS:
                streams = needed
                x = x[needed]
            block_mods = mods[MODS_PER_BLOCK * i : MODS_PER_BLOCK * (i + 1)]
            if streams != ALL_STREAMS:
                block_mods = [m[streams] for m in block_mods]
            x = block(x, block_mods, kv, ctx.cond_mask, self.key_valid, streams)
        return x, streams

    def _decode_streams(self, x: Tensor, streams: slice, shift: Tensor, scale: Tensor, need_action: bool,
                        need_vision: bool) -> tuple[Tensor | None, Tensor | None]:
        """Velocities of a two-stream model: each modality is its own stream, decoded with that stream's AdaLN."""
        present = range(2)[streams]  # stream index -> row of x
        v_a = v_o = None
        if need_action:
            row = present.index(ACTION_STREAM)
            v_a = self.action_out(x[row, :, 1:self.n_action_tokens], shift[ACTION_STREAM], scale[ACTION_STREAM])
        if need_vision:
            row = present.index(VISION_STREAM)
            v_o = self.vision_out(x[row, :, :self.config.n_vision_tokens], shift[VISION_STREAM], scale[VISION_STREAM])
        return v_a, v_o

    def _decode_single_stream(self, x: Tensor, shift: Tensor, scale: Tensor, need_action: bool,
                              need_vision: bool) -> tuple[Tensor | None, Tensor | None]:
        """Velocities of a single-stream model: the modalities are token ranges of stream 0 (decoded with the
        AdaLN vector of each token's own modality in the decoupled variant, one shared vector otherwise)."""
        n_a = self.n_action_tokens
        per_token = shift.shape[2] > 1
        v_a = v_o = None
        if need_action:
            rows = slice(1, n_a) if per_token else slice(None)
            v_a = self.action_out(x[0, :, 1:n_a], shift[0, :, rows], scale[0, :, rows])
        if need_vision:
            rows = slice(n_a, None) if per_token else slice(None)
            v_o = self.vision_out(x[0, :, n_a:], shift[0, :, rows], scale[0, :, rows])
        return v_a, v_o

    def compute_loss(self, batch: TensorDict, generator: torch.Generator | None = None,
                     shard: Shard = WHOLE_BATCH) -> TensorDict:
        """Decoupled flow-matching loss of one batch.

        Args:
            batch: keys listed in the module docstring (``future_tokens`` unused by action_only).
            generator: random source of tau and noise (tau_A, tau_o, eps_A, eps_o in that order).
            shard: ``batch`` is this shard of a data-parallel batch; its noise is the whole batch's, sliced.

        Returns:
            TensorDict with scalar ``loss`` (to minimise), ``loss_action`` and ``loss_vision``.
        """
        cfg = self.config
        action = batch[BATCH_ACTION_CHUNK_KEY]
        b, device = action.shape[0], action.device
        has_action = batch.get(HAS_ACTION_KEY, None)
        valid = action_validity(b, cfg.horizon, has_action, batch.get(ACTION_IS_PAD_KEY, None), device)
        ctx = self.encode_context(batch[BATCH_STATE_KEY], batch[COND_TOKENS_KEY], batch.get(COND_MASK_KEY, None))

        tau_a = sample_tau(b, s=cfg.tau_s, alpha=cfg.tau_alpha, generator=generator, device=device, shard=shard)
        tau_o = sample_tau(b, s=cfg.tau_s, alpha=cfg.tau_alpha, generator=generator, device=device, shard=shard)
        if not cfg.decoupled:
            tau_o = tau_a
        eps_a = cpu_drawn(torch.randn, *action.shape, generator=generator, device=device, shard=shard)
        noisy_action = interpolate(action, eps_a, tau_a)
        if has_action is not None:
            # No action to interpolate towards: the action tokens are pure noise.
            noisy_action = torch.where(has_action.view(-1, 1, 1), noisy_action, eps_a)
            if cfg.decoupled:
                tau_a = torch.where(has_action, tau_a, 0.0)

        noisy_vision = target_vision = None
        if cfg.has_vision:
            future = batch[FUTURE_TOKENS_KEY]
            eps_o = cpu_drawn(torch.randn, *future.shape, generator=generator, device=device, shard=shard)
            noisy_vision = interpolate(future, eps_o, tau_o)
            target_vision = velocity_target(future, eps_o)
        v_a, v_o = self(ctx, noisy_action, noisy_vision, tau_a, tau_o if cfg.has_vision else None)
        losses = decoupled_loss(v_a, velocity_target(action, eps_a), valid, v_o, target_vision, cfg.lambda_wm)
        return TensorDict(losses, batch_size=[])

    @torch.no_grad()
    def predict_action(
        self,
        obs: TensorDict,
        schedule: list[DenoiseStep],
        generator: torch.Generator | None = None,
        callback: Callable[[DenoiseStep, torch.Tensor, torch.Tensor | None], None] | None = None,
        noise_scale: float = 1.0,
        vision_source: VisionSource | None = None,
    ) -> TensorDict:
        """Sample an action chunk (and, with a vision stream, the predicted future tokens).

        Args:
            obs: ``state``, ``cond_tokens`` and optionally ``cond_mask``, ``action_noise`` [B, H, Da] and
                ``vision_noise`` [B, N_o, Dv] (the initial noises, :func:`.samplers.run_schedule`).
            schedule: the sampler's steps (:func:`.samplers.schedule_for`), e.g. ``async_schedule(4, 8)`` for
                test-time scaling to N_o = 32 vision steps.
            generator: random source of the initial noise; same seed, same chunk.
            callback: called after every denoising step (see :func:`.samplers.run_schedule`).
            noise_scale: factor on the drawn initial action noise (a sampling temperature).
            vision_source: vision tokens fed at each step instead of the integrated ones
                (:data:`.samplers.VisionSource`).

        Returns:
            TensorDict [B] with ``action_chunk`` [B, H, Da] and, unless action_only,
            ``future_tokens`` [B, N_o, Dv].
        """
        ctx = self.encode_context(obs[BATCH_STATE_KEY], obs[COND_TOKENS_KEY], obs.get(COND_MASK_KEY, None))
        action, vision = run_schedule(self, ctx, schedule, generator, callback, obs.get(BATCH_ACTION_NOISE_KEY, None),
                                      noise_scale, vision_source, obs.get(VISION_NOISE_KEY, None))
        out = {BATCH_ACTION_CHUNK_KEY: action}
        if vision is not None:
            out[FUTURE_TOKENS_KEY] = vision
        return TensorDict(out, batch_size=[ctx.batch_size])
