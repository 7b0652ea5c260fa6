"""Numerical precision of the trunk: float32, or bfloat16 autocast (``--runtime.precision bf16``).

Why bf16 and not fp16: bfloat16 keeps float32's exponent range, so flow-matching losses and velocities
need no loss scaling, and weights, optimiser state and policy files stay float32 (autocast only runs
matrix products and attention in bf16). It pays on GPUs with bf16 tensor cores. Measured on this
project's 2-core CPU (AVX512-BF16, no AMX; BENCHMARKS.md): training steps 22% faster, batch-1 sampling
20% slower, so the default stays fp32.
"""

from __future__ import annotations

import contextlib
from typing import Literal

import torch

Precision = Literal["fp32", "bf16"]


def autocast(device: torch.device, precision: Precision) -> contextlib.AbstractContextManager:
    """The context in which the trunk runs at ``precision`` on ``device``."""
    if precision == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
