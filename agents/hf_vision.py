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

from .image_encoder import ImageEncoder

PROCESSOR_FILE = "preprocessor_config.json"


def build_transformers_config(config: dict):
    """A ``transformers`` config from its ``to_dict()`` form (no download)."""
    from transformers import AutoConfig

    config = dict(config)
    return AutoConfig.for_model(config.pop("model_type"), **config)


class TransformersImageEncoder(ImageEncoder):
    """Patch embeddings of a ``transformers`` vision model.

    Args:
        path: local model folder; its ``preprocessor_config.json`` supplies the pixel mean/std.
        config: a ``transformers`` config (object or ``to_dict()`` form) to build a randomly
            initialised model instead, e.g. for tests; exactly one of ``path`` and ``config``.
        mean: per-channel pixel mean, overriding the processor's (default 0.5).
        std: per-channel pixel std, overriding the processor's (default 0.5).
    """

    def __init__(self, path: str | pathlib.Path | None = None, config=None,
                 mean: Sequence[float] | None = None, std: Sequence[float] | None = None) -> None:
        super().__init__()
        from transformers import AutoModel

        if (path is None) == (config is None):
            raise ValueError("give exactly one of path (pretrained weights) and config (random init)")
        processor = {}
        if path is not None:
            model = AutoModel.from_pretrained(path)
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
