"""SB3's scalars through torchrl's loggers, so ``dust-rl finetune`` logs as ``dust-rl train`` does.

An SB3 algorithm logs through its own ``Logger`` (``agent.logger.record`` ... ``dump``), which writes to output
formats. :class:`TorchrlOutput` is one such format that hands each numeric value to a torchrl ``Logger``
(:mod:`dust_rl.runtime.loggers`), so one ``--loggers`` option and one set of files (CSV, TensorBoard, wandb,
mlflow) serve training and fine-tuning. A value SB3 excludes from a format of the same name (``exclude=
"tensorboard"``: counters that are already the step) is left out of that logger too; text and media are left out.
"""

from __future__ import annotations

import numbers
import pathlib
from collections.abc import Iterable
from typing import Any

from stable_baselines3.common.logger import KVWriter
from stable_baselines3.common.logger import Logger as SB3Logger
from torchrl.record.loggers import Logger

from dust_rl.runtime.loggers import make_loggers

EXPERIMENT = "finetune"  # the loggers' experiment name: logs/finetune/ beside training's logs/train/


class TorchrlOutput(KVWriter):
    """An SB3 output format writing every numeric value to ``logger`` (of kind ``kind``) at SB3's step."""

    def __init__(self, logger: Logger, kind: str) -> None:
        self.logger, self.kind = logger, kind

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        for key, value in key_values.items():
            excluded = key_excluded.get(key) or ()
            if isinstance(value, numbers.Real) and self.kind not in excluded:
                self.logger.log_scalar(key, float(value), step=step)

    def close(self) -> None:
        """torchrl's loggers flush each scalar as it is written; nothing is left to close."""


def sb3_logger(kinds: Iterable[str], folder: pathlib.Path) -> SB3Logger:
    """An SB3 logger whose scalars go to torchrl loggers of ``kinds`` under ``folder``."""
    kinds = list(kinds)
    outputs = [TorchrlOutput(logger, kind) for logger, kind in zip(make_loggers(kinds, folder, EXPERIMENT), kinds)]
    return SB3Logger(str(folder), outputs)
