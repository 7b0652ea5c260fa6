"""Pretrain the frozen image encoder (a small conv autoencoder) on dataset frames, self-supervised.

No pretrained image weights can be downloaded, so DUST's frozen image
backbone is learnt here from the project's own environment frames: every
camera's frames are reconstructed through the 4x4 token bottleneck. One
episode in ``holdout_every`` is kept out of training to report an honest
reconstruction error. After training, the latent's per-channel statistics
over training frames are stored with the encoder, so its tokens come out
standardised (flow matching targets of unit scale).
"""

from __future__ import annotations

import math
import pathlib
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from dust_rl.agents import AutoencoderConfig, ConvAutoencoder, save_image_encoder
from dust_rl.agents.encoders.image_encoder import to_unit_float
from dust_rl.data import DemoDataset
from dust_rl.errors import ConfigError
from dust_rl.keys import IMAGE_KEY


def episode_split(dataset: DemoDataset, holdout_every: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows of a dataset's training and held-out episodes: every ``holdout_every``-th episode held out (0:
    none), so a held-out error is measured on layouts the fit never saw."""
    episode = torch.repeat_interleave(torch.arange(dataset.num_episodes), dataset.lengths)
    held = (episode + 1) % holdout_every == 0 if holdout_every else torch.zeros(len(episode), dtype=torch.bool)
    return (~held).nonzero().squeeze(1), held.nonzero().squeeze(1)


class FramePool:
    """Frames of every camera of some datasets, split by episode into training and held-out frames.

    A frame is one (row, camera) pair; frames are numbered across datasets, rows, then cameras.

    Args:
        datasets: the datasets.
        holdout_every: every ``holdout_every``-th episode of each dataset is held out (0: none).
    """

    def __init__(self, datasets: Sequence[DemoDataset], holdout_every: int = 10) -> None:
        self.datasets = list(datasets)
        self.train: list[torch.Tensor] = []  # per dataset, its training rows
        self.heldout: list[torch.Tensor] = []
        for dataset in self.datasets:
            train, heldout = episode_split(dataset, holdout_every)
            self.train.append(train)
            self.heldout.append(heldout)

    def count(self, split: list[torch.Tensor]) -> int:
        """Number of frames in a split."""
        return sum(len(rows) * len(d.cameras) for rows, d in zip(split, self.datasets))

    def gather(self, split: list[torch.Tensor], frames: torch.Tensor, size: int) -> torch.Tensor:
        """Float images [n, 3, size, size] in [0, 1] of the numbered ``frames`` of ``split``."""
        out = torch.empty(len(frames), 3, size, size)
        offset = 0
        for rows, dataset in zip(split, self.datasets):
            n_cams = len(dataset.cameras)
            local = frames - offset
            for c, cam in enumerate(dataset.cameras):
                sel = ((local >= 0) & (local < len(rows) * n_cams) & (local % n_cams == c)).nonzero().squeeze(1)
                if len(sel):
                    out[sel] = to_unit_float(dataset.data.get((*IMAGE_KEY, cam))[rows[local[sel] // n_cams]], size)
            offset += len(rows) * n_cams
        return out

    def sample(self, n: int, size: int, generator: torch.Generator) -> torch.Tensor:
        """``n`` random training frames."""
        return self.gather(self.train, torch.randint(self.count(self.train), (n,), generator=generator), size)

    def heldout_frames(self, n: int, size: int, generator: torch.Generator) -> torch.Tensor:
        """Up to ``n`` distinct random held-out frames."""
        frames = torch.randperm(self.count(self.heldout), generator=generator)[:n]
        return self.gather(self.heldout, frames, size)


@dataclass
class PretrainReport:
    """What a pretraining run did and how well it reconstructs."""

    path: pathlib.Path
    steps: int
    seconds: float
    train_loss: float
    heldout_loss: float | None
    train_frames: int


def check_fit_settings(steps: int, batch_size: int, warmup: int, lr: float) -> None:
    """Raise :class:`ConfigError` unless a fit's counts and rate are usable (shared by every fit on frames)."""
    if steps < 1 or batch_size < 1 or warmup < 0 or not (math.isfinite(lr) and lr > 0):
        raise ConfigError(f"steps and batch_size must be >= 1, warmup >= 0 and lr a finite number > 0, "
                          f"got {steps}, {batch_size}, {warmup} and {lr}")


def cosine_with_warmup(steps: int, warmup: int):
    """LR multiplier: linear warm-up, then cosine decay to 0."""
    return lambda s: min(1.0, (s + 1) / max(1, warmup)) * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps))


@torch.no_grad()
def standardise_latent(model: ConvAutoencoder, pool: FramePool, n_frames: int, generator: torch.Generator) -> None:
    """Set the encoder's latent statistics from ``n_frames`` training frames."""
    frames = pool.sample(n_frames, model.image_size, generator).to(_device_of(model))
    latent = torch.cat([model.raw_latent(chunk) for chunk in frames.split(256)])
    channels = latent.transpose(0, 1).flatten(1)
    model.set_latent_stats(channels.mean(1), channels.std(1))


@torch.no_grad()
def heldout_loss(model: ConvAutoencoder, pool: FramePool, n_frames: int, generator: torch.Generator) -> float | None:
    """Mean pixel MSE on held-out frames (None without any)."""
    if not pool.count(pool.heldout):
        return None
    frames = pool.heldout_frames(n_frames, model.image_size, generator).to(_device_of(model))
    return float(torch.stack([model.reconstruction_loss(chunk) for chunk in frames.split(256)]).mean())


def pretrain_encoder(datasets: Sequence[DemoDataset], out: str | pathlib.Path,
                     config: AutoencoderConfig = AutoencoderConfig(), steps: int = 3000, batch_size: int = 64,
                     lr: float = 2e-3, warmup: int = 100, seed: int = 0, holdout_every: int = 10,
                     progress: bool = True, command: str | None = None,
                     device: torch.device | str = "cpu") -> PretrainReport:
    """Train a :class:`ConvAutoencoder` on the datasets' frames and write it atomically to ``out``.

    Args:
        datasets: frame sources (all cameras are used).
        out: encoder file for ``make_policy(image_encoder=...)``.
        config: autoencoder shape; frames are resized to ``config.image_size``.
        steps: optimiser steps.
        batch_size: frames per step.
        lr: peak AdamW learning rate (cosine schedule after ``warmup`` steps).
        warmup: linear warm-up steps.
        seed: seeds the weights and the frame sampling.
        holdout_every: hold out every n-th episode for the held-out loss (0: none).
        progress: show a progress bar.
        command: the command line, kept in the file for provenance.
        device: where the autoencoder trains (frames are read and drawn on the CPU; the file is written from
            the CPU).

    Raises:
        ConfigError: a count or rate out of range, or an image size the latent grid does not divide.
    """
    check_fit_settings(steps, batch_size, warmup, lr)
    try:
        config.stage_channels()
    except ValueError as err:
        raise ConfigError(f"encoder shape: {err}") from err
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    pool = FramePool(datasets, holdout_every)
    model = ConvAutoencoder(config).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, cosine_with_warmup(steps, warmup))
    start, recent = time.perf_counter(), []
    bar = tqdm(range(steps), desc="pretraining encoder", disable=not progress)
    for _ in bar:
        loss = model.reconstruction_loss(pool.sample(batch_size, config.image_size, generator).to(device))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        recent = [*recent[-49:], loss.item()]
        bar.set_postfix(mse=f"{sum(recent) / len(recent):.5f}")
    model.eval()
    seconds = time.perf_counter() - start
    standardise_latent(model, pool, 2048, generator)
    report = PretrainReport(pathlib.Path(out), steps, seconds, sum(recent) / len(recent),
                            heldout_loss(model, pool, 1024, generator), pool.count(pool.train))
    info = {"datasets": [str(d.root) for d in pool.datasets], "steps": steps, "batch_size": batch_size, "lr": lr,
            "seed": seed, "train_frames": report.train_frames, "train_mse": report.train_loss,
            "heldout_mse": report.heldout_loss, "seconds": round(seconds, 1), "command": command}
    save_image_encoder(model.cpu(), out, info)
    return report


def _device_of(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device
