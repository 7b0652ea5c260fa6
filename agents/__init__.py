"""DUST agents: dual-stream flow-matching trunk, baselines, samplers, losses."""

from .batch import random_batch
from .config import VARIANTS, DustConfig
from .dust_agent import DustAgent
from .dust_model import ChunkContext, DustModel
from .flow_matching import action_validity, decoupled_loss, interpolate, masked_mse, sample_tau, velocity_target
from .samplers import DenoiseStep, action_only_schedule, async_schedule, run_schedule, schedule_for, sync_schedule

__all__ = [
    "VARIANTS",
    "ChunkContext",
    "DenoiseStep",
    "DustAgent",
    "DustConfig",
    "DustModel",
    "action_only_schedule",
    "action_validity",
    "async_schedule",
    "decoupled_loss",
    "interpolate",
    "masked_mse",
    "random_batch",
    "run_schedule",
    "sample_tau",
    "schedule_for",
    "sync_schedule",
    "velocity_target",
]
