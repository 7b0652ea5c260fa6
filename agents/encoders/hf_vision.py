"""Vision transformers from ``transformers`` (SigLIP, DINOv2, ...) as frozen image encoders.

The paper's future targets are SigLIP-2 patch embeddings (DINOv2 worked as
well); this adapter lets a user plug such a model in from a local folder.
Patch tokens are laid back onto their grid and pooled like any other feature
map; prefix tokens ([CLS], registers) are dropped.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import torch
from torch import Tensor

from ..config import MAX_ENCODER_LAYERS, MAX_IMAGE_SIZE, MAX_PARAMETERS, MAX_WIDTH, check_size
from .image_encoder import ImageEncoder
from .text_encoder import pretrained_model

PROCESSOR_FILE = "preprocessor_config.json"
# ViT-shaped vision models (patch embedding, ``image_size``, ``patch_size``) that a stored config may build.
VISION_MODEL_TYPES = ("vit", "dinov2", "dinov2_with_registers", "siglip_vision_model", "clip_vision_model")


def build_transformers_config(config: dict):
    """A ``transformers`` config from its ``to_dict()`` form (no download), checked by :func:`check_vision_config`."""
    from transformers import AutoConfig

    config = dict(config)
    model_type = config.pop("model_type", None)
    if model_type not in VISION_MODEL_TYPES:
        raise ValueError(f"vision model type {model_type!r} cannot be built from a stored config; "
                         f"expected one of {VISION_MODEL_TYPES}")
    built = AutoConfig.for_model(model_type, **config)
    check_vision_config(built)
    return built


def check_vision_config(config) -> None:
    """Raise ``ValueError`` if a ViT config's sizes exceed the caps of :mod:`..config` (before any weight exists)."""
    hidden, layers = config.hidden_size, config.num_hidden_layers
    check_size("hidden_size", hidden, MAX_WIDTH)
    check_size("num_hidden_layers", layers, MAX_ENCODER_LAYERS)
    check_size("num_attention_heads", config.num_attention_heads, hidden)
    check_size("image_size", config.image_size, MAX_IMAGE_SIZE)
    check_size("patch_size", config.patch_size, config.image_size)
    # DINOv2 sizes its MLP by mlp_ratio, the others by intermediate_size; a stored config may carry both.
    mlp = int(max(getattr(config, "intermediate_size", None) or 0, hidden * (getattr(config, "mlp_ratio", None) or 0)))
    check_size("MLP width", mlp, 4 * MAX_WIDTH)
    patches = (config.image_size // config.patch_size) ** 2
    # Dominant weights: attention and MLP per layer, position and patch embeddings.
    parameters = layers * (4 * hidden**2 + 2 * hidden * mlp) + (patches + 3 * config.patch_size**2) * hidden
    if parameters > MAX_PARAMETERS:
        raise ValueError(f"the vision model would have about {parameters:.3g} parameters, more than the cap of "
                         f"{MAX_PARAMETERS:.3g}")


class TransformersImageEncoder(ImageEncoder):
    """Patch embeddings of a ``transformers`` vision model.

    Args:
        path: local model folder; its ``preprocessor_config.json`` supplies the pixel mean/std.
        config: a ``transformers`` config (object or ``to_dict()`` form) to build a randomly
            initialised model instead, e.g. for tests; exactly one of ``path`` and ``config``.
        mean: per-channel pixel mean, overriding the processor's (default 0.5).
        std: per-channel pixel std, overriding the processor's (default 0.5).

    Raises:
        ValueError: ``path`` is not a local folder of safetensors weights (nothing is downloaded, nothing unpickled;
            :func:`~.text_encoder.pretrained_model`), or a config in
            ``to_dict()`` form (as stored in a policy file) of another model type or beyond the size caps.
    """

    def __init__(self, path: str | pathlib.Path | None = None, config=None,
                 mean: Sequence[float] | None = None, std: Sequence[float] | None = None) -> None:
        super().__init__()
        from transformers import AutoModel

        if (path is None) == (config is None):
            raise ValueError("give exactly one of path (pretrained weights) and config (random init)")
        processor = {}
        if path is not None:
            model = pretrained_model(path)
            if (pathlib.Path(path) / PROCESSOR_FILE).is_file():
                processor = json.loads((pathlib.Path(path) / PROCESSOR_FILE).read_text())
        else:
            model = AutoModel.from_config(build_transformers_config(config) if isinstance(config, dict) else config)
        self.model = getattr(model, "vision_model", model).eval()  # a dual-encoder (SigLIP) keeps its vision half
        vision_config = self.model.config
        self.path = None if path is None else str(path)
        self.dim, self.image_size = int(vision_config.hidden_size), int(vision_config.image_size)
        self.patch_size = int(vision_config.patch_size)
        mean = processor.get("image_mean", [0.5] * 3) if mean is None else mean
        std = processor.get("image_std", [0.5] * 3) if std is None else std
        self.register_buffer("pixel_mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("pixel_std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

    def feature_map(self, images: Tensor) -> Tensor:
        side = self.image_size // self.patch_size
        hidden = self.model(pixel_values=(images - self.pixel_mean) / self.pixel_std).last_hidden_state
        patches = hidden[:, -side * side:]  # prefix tokens come first
        return patches.transpose(1, 2).reshape(hidden.shape[0], self.dim, side, side)

    def reference(self) -> dict:
        ref = {"kind": "transformers_vision", "path": self.path,
               "mean": self.pixel_mean.flatten().tolist(), "std": self.pixel_std.flatten().tolist()}
        if self.path is None:
            ref["config"] = self.model.config.to_dict()
        return ref
