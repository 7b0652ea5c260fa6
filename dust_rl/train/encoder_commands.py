"""The image-encoder commands of ``dust-rl``: ``pretrain-encoder`` (a conv autoencoder on dataset frames) and
``encoder check|info`` (linear probes of the frozen tokens, size and speed)."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Annotated

import tyro

from dust_rl.errors import ConfigError, check_at_least
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.runtime.loggers import LoggerKind, check_loggers
from dust_rl.runtime.settings import RuntimeSettings, runtime_field


@dataclass
class PretrainEncoderCommand:
    """Pretrain the frozen image encoder (conv autoencoder) on dataset frames and write it to one file."""

    dataset: tuple[pathlib.Path, ...]
    """Dataset folders."""
    out: pathlib.Path
    """Encoder file (written atomically)."""
    steps: int = 3000
    """Optimiser steps."""
    batch_size: int = 64
    """Frames per step."""
    lr: float = 2e-3
    """Learning rate."""
    seed: int = 0
    """Seed of the weights and batches."""
    image_size: int = 128
    """Frames are resized to this."""
    grid: int = 4
    """Latent token grid side."""
    dim: int = 64
    """Token size."""
    width: int = 16
    """Channels of the first conv stage."""
    runtime: RuntimeSettings = runtime_field()
    """Where the autoencoder trains (`--runtime.device`), torch threads, progress bar."""

    def __post_init__(self) -> None:
        self.runtime.check_fp32("dust-rl pretrain-encoder")


def run_pretrain_encoder(config: PretrainEncoderCommand, command_line: str) -> None:
    from dust_rl.agents import AutoencoderConfig
    from dust_rl.agents.encoders.backbone import IMAGE_ENCODER_KIND
    from dust_rl.data import DemoDataset
    from dust_rl.storage.checkpoint_files import check_replaceable_file
    from dust_rl.train.pretrain_encoder import pretrain_encoder

    if not config.dataset:
        raise ConfigError("give at least one --dataset folder")
    check_replaceable_file(config.out, IMAGE_ENCODER_KIND)  # before training, not after it
    encoder = AutoencoderConfig(image_size=config.image_size, latent_grid=config.grid, dim=config.dim,
                                width=config.width)
    with torch_threads(config.runtime.thread_count):
        report = pretrain_encoder([DemoDataset(d) for d in config.dataset], config.out, encoder, steps=config.steps,
                                  batch_size=config.batch_size, lr=config.lr, seed=config.seed,
                                  progress=config.runtime.progress, command=command_line,
                                  device=resolve_device(config.runtime.device))
    heldout = "n/a" if report.heldout_loss is None else f"{report.heldout_loss:.5f}"
    print(f"{report.path}: {report.steps} steps in {report.seconds:.0f} s on {report.train_frames} frames; "
          f"pixel MSE train {report.train_loss:.5f}, held-out {heldout}")


@dataclass
class EncoderCheck:
    """Linear probes: how well each camera's frozen tokens give the objects' positions (probe.json, probe.png)."""

    dataset: pathlib.Path
    """Dataset folder (its rows hold the objects' positions)."""
    image_encoder: str | None = None
    """Encoder name or file (default: the policies' default)."""
    grid: tuple[int, int] | None = None
    """Token grid (default: the encoder's own)."""
    every: int = 8
    """Probe every n-th row."""
    out: pathlib.Path = pathlib.Path("runs/encoder_check")
    """Folder for probe.json and probe.png."""

    def run(self, command_line: str) -> None:
        from dust_rl.agents.encoders.backbone import resolve_image_encoder
        from dust_rl.data import DemoDataset
        from dust_rl.train.encoder_check import probe_dataset, write_encoder_check

        check_at_least(self, 1, "every")
        dataset, encoder = DemoDataset(self.dataset), resolve_image_encoder(self.image_encoder)
        grid = tuple(self.grid) if self.grid else encoder.native_grid()
        results = probe_dataset(dataset, encoder, grid, every=self.every)
        title = f"{self.image_encoder or 'default encoder'}, {grid[0]}x{grid[1]} tokens, {dataset.root.name}"
        paths = write_encoder_check(results, self.out, title)
        for camera, result in results.items():
            values = " ".join(f"{v:.2f}" for v in result.r2.tolist())
            print(f"{camera}: held-out R^2 per environment-state column [{values}] (mean {result.r2.mean():.2f})")
        print(f"{paths['plot']}\n{paths['json']}")


@dataclass
class EncoderInfo:
    """An image encoder's size, token grid, speed on this machine and feature-cache size per 1,000 frames."""

    image_encoder: str | None = None
    """Encoder name or file (default: the policies' default)."""
    frames: int = 32
    """Frames per timed batch (the median of 5 batches is reported)."""

    def run(self, command_line: str) -> None:
        import statistics
        import time

        import torch

        from dust_rl.agents.encoders.backbone import resolve_image_encoder

        check_at_least(self, 1, "frames")
        encoder = resolve_image_encoder(self.image_encoder)
        grid = encoder.native_grid()
        images = torch.randint(0, 256, (self.frames, 3, encoder.image_size, encoder.image_size), dtype=torch.uint8)
        seconds = []
        with torch.no_grad():
            for _ in range(6):  # the first call warms up and is not counted
                began = time.perf_counter()
                encoder.feature_map(images.float() / 255)
                seconds.append(time.perf_counter() - began)
        cache = 1000 * grid[0] * grid[1] * encoder.dim * 2  # float16 tokens of one camera
        print(f"{self.image_encoder or 'default encoder'}: {sum(p.numel() for p in encoder.parameters()):,} "
              f"parameters, {encoder.image_size} px -> {grid[0]}x{grid[1]} tokens of {encoder.dim}; "
              f"{1e3 * statistics.median(seconds[1:]) / self.frames:.2f} ms/frame at {torch.get_num_threads()} "
              f"threads; feature cache {cache / 2**20:.1f} MiB per 1,000 frames per camera")


@dataclass
class EncoderFitDecoder:
    """Fit a decoder from a policy's future tokens to pixels on a dataset's frames, so eval videos and `dust-rl
    diagnose world-model` show its predicted futures (the policy is only read)."""

    policy: pathlib.Path
    """Policy file with a vision stream (`dust-rl train`)."""
    dataset: pathlib.Path
    """Dataset with the policy's cameras (its training data will do)."""
    out: pathlib.Path | None = None
    """Decoder file (written atomically; a PNG of held-out frames and `logs/` go beside it); default:
    `token_decoder.pt` beside the policy, where eval and diagnose look for it."""
    steps: int = 2000
    """Optimiser steps."""
    batch_size: int = 64
    """Frames per step."""
    lr: float = 2e-3
    """Peak learning rate (linear warm-up, then cosine)."""
    image_size: int = 64
    """Side of the images drawn (the vision grid times a power of 2)."""
    seed: int = 0
    """Seed of the weights and batches."""
    loggers: tuple[LoggerKind, ...] = ("csv", "tensorboard")
    """Where the losses and the held-out frames go (`logs/` beside the decoder file)."""
    runtime: RuntimeSettings = runtime_field()
    """Where the decoder trains (`--runtime.device`), torch threads, progress bars."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "steps", "batch_size", "image_size")
        check_loggers(self.loggers)
        self.runtime.check_fp32("dust-rl encoder fit-decoder")

    def run(self, command_line: str) -> None:
        from dust_rl.agents import load_policy
        from dust_rl.agents.encoders.token_decoder import TOKEN_DECODER_FILE, TOKEN_DECODER_KIND
        from dust_rl.data import DemoDataset
        from dust_rl.storage.checkpoint_files import check_replaceable_file
        from dust_rl.train.token_decoder_fit import fit_token_decoder

        out = self.out or self.policy.parent / TOKEN_DECODER_FILE
        check_replaceable_file(out, TOKEN_DECODER_KIND)  # before the fit, not after it
        dataset = DemoDataset(self.dataset)
        with torch_threads(self.runtime.thread_count):
            policy = load_policy(self.policy).to(resolve_device(self.runtime.device)).eval()
            dataset.check_fits_policy(policy.info, self.policy)
            fit = fit_token_decoder(policy, dataset, out, self.image_size, self.steps, self.batch_size, self.lr,
                                    seed=self.seed, loggers=self.loggers, progress=self.runtime.progress,
                                    command=command_line, device=resolve_device(self.runtime.device))
        against = ("" if fit.heldout_mse is None else
                   f", held-out {fit.heldout_mse:.5f} (the mean frame: {fit.mean_frame_mse:.5f})")
        print(f"{fit.path}: {fit.steps} steps in {fit.seconds:.0f} s on {fit.train_rows} frames; pixel MSE train "
              f"{fit.train_mse:.5f}{against}; held-out frames: {fit.path.with_suffix('.png')}")


@dataclass
class EncoderCommand:
    """Diagnose frozen image encoders, or fit a decoder of a policy's future tokens."""

    action: (Annotated[EncoderCheck, tyro.conf.subcommand("check")]
             | Annotated[EncoderInfo, tyro.conf.subcommand("info")]
             | Annotated[EncoderFitDecoder, tyro.conf.subcommand("fit-decoder")])
    """What to do."""


def run_encoder(config: EncoderCommand, command_line: str) -> None:
    config.action.run(command_line)
