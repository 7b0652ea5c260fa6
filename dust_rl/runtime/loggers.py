"""Where a run's scalars go: torchrl's loggers, shared by ``dust-rl train`` and ``dust-rl finetune``.

One option (``--loggers csv tensorboard wandb mlflow``) and one stack (torchrl's ``get_logger``, each logger
writing under the run's ``logs/``) serve every command that logs scalars. wandb and mlflow are optional
packages: :func:`check_loggers` refuses a missing one when the settings are read, before a run folder or
anything else is written, so a long run does not fail at its first scalar.

TensorBoard also takes what a run has beside its scalars (:func:`log_config`, :func:`log_image`,
:func:`log_video`); the other loggers get scalars only. A video goes to TensorBoard as an animated GIF image
summary, what ``SummaryWriter.add_video`` writes, encoded here with Pillow: ``add_video`` needs moviepy, which this
package does not install.
"""

from __future__ import annotations

import importlib.util
import io
import json
import pathlib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Literal, get_args

import numpy as np
from PIL import Image
from torchrl.record.loggers import Logger, TensorboardLogger, get_logger

from dust_rl.errors import ConfigError

LoggerKind = Literal["csv", "tensorboard", "wandb", "mlflow"]
# The package each logger imports, and what installs it.
LOGGER_PACKAGES = {"csv": None, "tensorboard": ("tensorboard", "tensorboard"), "wandb": ("wandb", "wandb"),
                   "mlflow": ("mlflow", "mlflow")}


def check_loggers(kinds: Iterable[str]) -> None:
    """Raise :class:`ConfigError` at an unknown logger or one whose package is not installed (naming the
    ``pip install`` to run)."""
    kinds = list(kinds)
    unknown = sorted(set(kinds) - set(get_args(LoggerKind)))
    if unknown:
        raise ConfigError(f"unknown loggers {unknown}; choose from {list(get_args(LoggerKind))}")
    for kind in kinds:
        package = LOGGER_PACKAGES[kind]
        if package is not None and importlib.util.find_spec(package[0]) is None:
            raise ConfigError(f"--loggers {kind} needs the {package[0]} package: pip install {package[1]}")


def check_run_name(name: str) -> None:
    """Raise :class:`ConfigError` unless ``name`` can name a run's folder of logs (one folder, inside the run's)."""
    if not name or name in (".", "..") or "/" in name or "\\" in name:
        raise ConfigError(f"--logging.run-name must name one folder (not empty, '.' or '..', no '/'), got {name!r}")


def make_loggers(kinds: Iterable[str], folder: pathlib.Path, experiment: str) -> list[Logger]:
    """One torchrl logger per kind, writing under ``folder`` as ``experiment``."""
    return [get_logger(kind, str(folder), experiment) for kind in kinds]


def log_scalars(loggers: Iterable[Logger], scalars: Mapping[str, float], step: int) -> None:
    """Every scalar to every logger, at ``step``."""
    for logger in loggers:
        for name, value in scalars.items():
            logger.log_scalar(name, value, step=step)


def log_config(loggers: Iterable[Logger], config: Mapping, metrics: Iterable[str]) -> None:
    """The run's ``config`` (JSON values) to TensorBoard: as text (the JSON) and as hparams, each setting by its
    dotted name (lists as text), beside the ``metrics`` (scalar tags) its HParams dashboard sets against them."""
    from torch.utils.tensorboard.summary import hparams

    flat = dict(_dotted(config))
    summaries = hparams(flat, dict.fromkeys(metrics, 0.0))
    text = "    " + json.dumps(config, indent=2).replace("\n", "\n    ")  # indented: a code block in markdown
    for writer in _tensorboard_writers(loggers):
        writer.add_text("config", text)
        for summary in summaries:  # as add_hparams writes them, but into this run rather than a run of their own
            writer._get_file_writer().add_summary(summary)


def log_image(loggers: Iterable[Logger], name: str, image: np.ndarray, step: int) -> None:
    """An RGB image ``[H, W, 3]`` uint8 to TensorBoard, at ``step``."""
    for writer in _tensorboard_writers(loggers):
        writer.add_image(name, image, step, dataformats="HWC")


def log_video(loggers: Iterable[Logger], name: str, frames: Sequence[np.ndarray], fps: float, step: int) -> None:
    """A video, RGB frames ``[H, W, 3]`` uint8 at ``fps``, to TensorBoard as an animated GIF image, at ``step``."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    writers = list(_tensorboard_writers(loggers))
    if not writers or not frames:
        return
    gif = io.BytesIO()
    first, *rest = (Image.fromarray(frame) for frame in frames)
    first.save(gif, format="GIF", save_all=True, append_images=rest, duration=round(1000 / fps), loop=0)
    height, width = frames[0].shape[:2]
    image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=gif.getvalue())
    for writer in writers:
        writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=name, image=image)]), step)


def _tensorboard_writers(loggers: Iterable[Logger]) -> Iterator:
    """The ``SummaryWriter`` of each TensorBoard logger among ``loggers``."""
    return (logger.experiment for logger in loggers if isinstance(logger, TensorboardLogger))


def _dotted(values: Mapping, prefix: str = "") -> Iterator[tuple[str, object]]:
    """Nested JSON ``values`` as (dotted name, value) pairs, lists as their text."""
    for key, value in values.items():
        if isinstance(value, Mapping):
            yield from _dotted(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", str(value) if isinstance(value, list) else value
