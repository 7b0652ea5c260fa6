"""Fit a :class:`~dust_rl.agents.encoders.token_decoder.TokenDecoder` for a policy, on a dataset's frames.

The decoder learns pixels of the policy's future camera from that camera's frozen tokens pooled as the policy's
world-model targets are (:meth:`~dust_rl.agents.DustPolicy.future_targets`), read from the dataset's feature cache
(training already wrote it; nothing is encoded twice). The policy itself is only read. One episode in
``holdout_every`` is kept out, and the report sets the held-out pixel error beside the error of the mean training
frame (what a decoder that learnt nothing would draw). The decoder's file gets a PNG of held-out frames beside it
(real, then decoded), which also goes to the loggers with the losses.
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.agents.encoders.image_encoder import to_unit_float
from dust_rl.agents.encoders.token_decoder import TokenDecoder, TokenDecoderConfig, save_token_decoder
from dust_rl.data import DemoDataset
from dust_rl.data.features import FeatureCache
from dust_rl.errors import ConfigError
from dust_rl.evaluate.video import image_panel, labelled_row
from dust_rl.keys import IMAGE_KEY
from dust_rl.runtime.loggers import log_image, log_scalars, make_loggers
from dust_rl.storage.atomic_files import atomic_write
from dust_rl.train.pretrain_encoder import check_fit_settings, cosine_with_warmup, episode_split

PANEL_ROWS = 6  # held-out frames in the PNG


@dataclass
class DecoderFit:
    """What a fit did and how well its decoder draws frames it never saw."""

    path: pathlib.Path
    steps: int
    seconds: float
    train_mse: float
    heldout_mse: float | None
    mean_frame_mse: float | None  # the mean training frame as the drawing of every held-out frame
    train_rows: int


class DecoderData:
    """A dataset's future-camera frames and their pooled tokens [rows, N_o, Dv], split by episode."""

    def __init__(self, policy: DustPolicy, dataset: DemoDataset, image_size: int, holdout_every: int,
                 progress: bool) -> None:
        features = FeatureCache(dataset, policy, progress=progress, store=True)
        self.tokens = torch.cat([policy.future_targets(chunk.float()) for chunk in features.image_tokens.split(4096)])
        self.frames = dataset.data.get((*IMAGE_KEY, policy.future_camera))
        self.image_size = image_size
        self.train, self.heldout = episode_split(dataset, holdout_every)

    def batch(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Tokens [n, N_o, Dv] and frames [n, 3, S, S] in [0, 1] of dataset rows."""
        return self.tokens[rows], to_unit_float(self.frames[rows], self.image_size)


def fit_token_decoder(policy: DustPolicy, dataset: DemoDataset, out: pathlib.Path, image_size: int = 64,
                      steps: int = 2000, batch_size: int = 64, lr: float = 2e-3, warmup: int = 100, seed: int = 0,
                      holdout_every: int = 10, loggers: tuple[str, ...] = ("csv", "tensorboard"),
                      progress: bool = True, command: str | None = None,
                      device: torch.device | str = "cpu") -> DecoderFit:
    """Fit a decoder of ``policy``'s future tokens on ``dataset`` and write it atomically to ``out``.

    Args:
        policy: a policy with a vision stream (only read).
        dataset: frames of the policy's cameras (its training data will do: the tokens are frozen).
        out: the decoder file; the PNG and ``logs/`` go beside it.
        image_size: side of the images drawn (the vision grid times a power of 2).
        steps, batch_size, lr, warmup: AdamW steps on rows drawn at random, peak rate, linear warm-up (then cosine).
        seed: seeds the weights and the rows drawn.
        holdout_every: every n-th episode is held out (0: none).
        loggers: torchrl loggers for the losses and the held-out frames (``logs/`` beside ``out``).
        device: where the decoder trains (tokens and frames are gathered on the CPU).

    Raises:
        ConfigError: a policy without a vision stream, or counts, rate or size out of range.
    """
    if not policy.config.has_vision:
        raise ConfigError(f"a {policy.config.variant} policy predicts no future to decode")
    rows, cols = policy.config.vision_grid
    check_fit_settings(steps, batch_size, warmup, lr)
    if rows != cols:
        raise ConfigError(f"decoder shape: the vision grid must be square, got {rows}x{cols}")
    config = TokenDecoderConfig(policy.backbone.image.reference(), rows, policy.config.vision_dim, image_size)
    try:
        config.stage_channels()
    except ValueError as err:
        raise ConfigError(f"decoder shape: {err}") from err
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    data = DecoderData(policy, dataset, image_size, holdout_every, progress)
    decoder = TokenDecoder(config)
    tokens = data.tokens[data.train]
    decoder.set_token_stats(tokens.mean((0, 1)), tokens.std((0, 1)))
    decoder.to(device)
    optimizer = torch.optim.AdamW(decoder.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, cosine_with_warmup(steps, warmup))
    logs = make_loggers(loggers, out.parent / "logs", "token_decoder")
    start, recent = time.perf_counter(), []
    for step in (bar := tqdm(range(steps), desc="fitting token decoder", disable=not progress)):
        batch_tokens, frames = data.batch(data.train[torch.randint(len(data.train), (batch_size,),
                                                                   generator=generator)])
        loss = (decoder(batch_tokens.to(device)) - frames.to(device)).square().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        recent = [*recent[-49:], loss.item()]
        if step % 50 == 0 or step == steps - 1:
            log_scalars(logs, {"decoder/train_mse": sum(recent) / len(recent)}, step)
            bar.set_postfix(mse=f"{sum(recent) / len(recent):.5f}")
    seconds = time.perf_counter() - start
    decoder.eval().cpu()
    heldout, mean_frame = heldout_errors(decoder, data, generator)
    report = DecoderFit(out, steps, seconds, sum(recent) / len(recent), heldout, mean_frame, len(data.train))
    info = {"dataset": str(dataset.root), "future_camera": policy.future_camera, "steps": steps,
            "batch_size": batch_size, "lr": lr, "seed": seed, "train_rows": report.train_rows,
            "train_mse": report.train_mse, "heldout_mse": heldout, "mean_frame_mse": mean_frame,
            "seconds": round(seconds, 1), "command": command}
    save_token_decoder(decoder, out, info)
    if len(data.heldout):
        panel = heldout_panel(decoder, data, generator)
        with atomic_write(out.with_suffix(".png"), "wb") as f:
            panel.save(f, format="PNG")
        log_image(logs, "decoder/heldout", np.asarray(panel), steps)
    if heldout is not None:
        log_scalars(logs, {"decoder/heldout_mse": heldout, "decoder/mean_frame_mse": mean_frame}, steps)
    return report


@torch.no_grad()
def heldout_errors(decoder: TokenDecoder, data: DecoderData, generator: torch.Generator,
                   count: int = 1024) -> tuple[float | None, float | None]:
    """Pixel MSE on up to ``count`` held-out rows: the decoder's, and the mean training frame's (None without any)."""
    if not len(data.heldout):
        return None, None
    rows = data.heldout[torch.randperm(len(data.heldout), generator=generator)[:count]]
    mean_frame = data.batch(data.train[torch.randperm(len(data.train), generator=generator)[:count]])[1].mean(0)
    errors, baseline = [], []
    for part in rows.split(256):
        tokens, frames = data.batch(part)
        errors.append((decoder(tokens) - frames).square().mean((1, 2, 3)))
        baseline.append((mean_frame - frames).square().mean((1, 2, 3)))
    return float(torch.cat(errors).mean()), float(torch.cat(baseline).mean())


@torch.no_grad()
def heldout_panel(decoder: TokenDecoder, data: DecoderData, generator: torch.Generator) -> Image.Image:
    """:data:`PANEL_ROWS` held-out frames, each row the real frame beside its decoding."""
    rows = data.heldout[torch.randperm(len(data.heldout), generator=generator)[:PANEL_ROWS]]
    tokens, frames = data.batch(rows)
    size = data.frames.shape[-1]
    lines = [labelled_row([("real", image_panel(frame, size)), ("decoded", image_panel(drawn, size))])
             for frame, drawn in zip(frames, decoder(tokens))]
    return Image.fromarray(np.concatenate(lines))
