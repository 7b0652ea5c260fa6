"""Where a policy's tensors live: the ``--runtime.device`` option of ``dust-rl train`` and ``dust-rl eval``.

``auto`` takes the first CUDA device when torch sees one, else Apple's MPS, else the CPU. An explicit
device that this torch cannot use is refused before any work starts, with what torch reports.
Policies, checkpoints and feature caches are stored on the CPU whatever the device (``load_policy``
maps to the CPU), and the sampling noise is drawn on the CPU (``agents.model.flow_matching.cpu_drawn``), so a
policy trained on a GPU evaluates on a CPU box and a seed means the same noise everywhere.
"""

from __future__ import annotations

import torch

from dust_rl.errors import ConfigError

DEVICE_HELP = "auto | cpu | cuda | cuda:N | mps"


def resolve_device(name: str) -> torch.device:
    """The torch device ``name`` stands for.

    Raises:
        ConfigError: an unknown name, or a device this machine's torch cannot use.
    """
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", 0)
        return torch.device("mps" if torch.backends.mps.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"unknown device {name!r}; expected {DEVICE_HELP}") from err
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if not count:
            raise ConfigError(f"device {name!r}: torch {torch.__version__} sees no CUDA device "
                              "(torch.cuda.is_available() is False); use --runtime.device cpu or auto")
        if device.index is not None and device.index >= count:
            raise ConfigError(f"device {name!r}: torch sees {count} CUDA device(s), numbered 0..{count - 1}")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"device {name!r}: MPS is not available on this machine; use --runtime.device cpu or auto")
    elif device.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"device {name!r}: only {DEVICE_HELP} are supported")
    return device
