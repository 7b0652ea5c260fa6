"""Imitation training: ``dust-rl train`` (:mod:`.imitation`), its cached features, batches and schedules.

``python -m dust_rl.train ARGS`` (e.g. under ``torchrun``) runs ``dust-rl train ARGS``.
"""

from dust_rl.train.imitation import TrainConfig, TrainSettings, train

__all__ = ["TrainConfig", "TrainSettings", "train"]
