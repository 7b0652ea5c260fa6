"""Imitation training: ``dust-rl train`` (:mod:`.imitation`), its settings (:mod:`.settings`) and named recipes
(:mod:`.recipes`), its cached features, batches and schedules.

``python -m dust_rl.train ARGS`` (e.g. under ``torchrun``) runs ``dust-rl train ARGS``.
"""

from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.settings import TrainSettings

__all__ = ["TrainConfig", "TrainSettings", "train"]
