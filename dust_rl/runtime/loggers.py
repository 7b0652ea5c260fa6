"""Where a run's scalars go: torchrl's loggers, shared by ``dust-rl train`` and ``dust-rl finetune``.

One option (``--loggers csv tensorboard wandb mlflow``) and one stack (torchrl's ``get_logger``, each logger
writing under the run's ``logs/``) serve every command that logs scalars. wandb and mlflow are optional
packages: :func:`check_loggers` refuses a missing one when the settings are read, before a run folder or
anything else is written, so a long run does not fail at its first scalar.
"""

from __future__ import annotations

import importlib.util
import pathlib
from collections.abc import Iterable, Mapping
from typing import Literal, get_args

from torchrl.record.loggers import Logger, get_logger

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


def make_loggers(kinds: Iterable[str], folder: pathlib.Path, experiment: str) -> list[Logger]:
    """One torchrl logger per kind, writing under ``folder`` as ``experiment``."""
    return [get_logger(kind, str(folder), experiment) for kind in kinds]


def log_scalars(loggers: Iterable[Logger], scalars: Mapping[str, float], step: int) -> None:
    """Every scalar to every logger, at ``step``."""
    for logger in loggers:
        for name, value in scalars.items():
            logger.log_scalar(name, value, step=step)
