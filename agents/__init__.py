"""DUST agents: the dual-stream trunk with its loss and sampler, baselines, frozen backbone, torchrl policy."""

from .config import VARIANTS, DustConfig, ModelConfig, PolicyConfig, SamplerConfig
from .encoders.autoencoder import AutoencoderConfig, ConvAutoencoder
from .encoders.backbone import FrozenBackbone, load_image_encoder, save_image_encoder
from .encoders.hf_vision import TransformersImageEncoder
from .encoders.image_encoder import ImageEncoder
from .encoders.text_encoder import TextEncoder, TransformersTextEncoder, pooled_text
from .execution import ChunkExecutor
from .factory import env_spec, load_policy, make_policy, save_policy
from .model.batch import random_batch
from .model.dust_model import ChunkContext, DustModel
from .model.flow_matching import action_validity, decoupled_loss, interpolate, masked_mse, sample_tau, velocity_target
from .model.samplers import DenoiseStep, action_only_schedule, async_schedule, run_schedule, schedule_for, sync_schedule
from .policy import DustPolicy

__all__ = [
    "VARIANTS",
    "AutoencoderConfig",
    "ChunkContext",
    "ChunkExecutor",
    "ConvAutoencoder",
    "DenoiseStep",
    "DustConfig",
    "DustModel",
    "DustPolicy",
    "ModelConfig",
    "PolicyConfig",
    "SamplerConfig",
    "FrozenBackbone",
    "ImageEncoder",
    "TextEncoder",
    "TransformersImageEncoder",
    "TransformersTextEncoder",
    "pooled_text",
    "action_only_schedule",
    "action_validity",
    "async_schedule",
    "decoupled_loss",
    "env_spec",
    "interpolate",
    "load_image_encoder",
    "load_policy",
    "make_policy",
    "masked_mse",
    "random_batch",
    "run_schedule",
    "sample_tau",
    "save_image_encoder",
    "save_policy",
    "schedule_for",
    "sync_schedule",
    "velocity_target",
]
