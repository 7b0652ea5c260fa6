"""What a speed figure was measured on: the CPU, the vector instructions torch's kernels use, torch's threads.

AVX2 and AVX-512 CPUs differ in speed (MKL's matrix products, torch's own kernels, oneDNN's convolutions, MuJoCo's
software renderer), so every speed table names the machine with this line. An AVX-512 machine runs the AVX2 code
paths with ``ATEN_CPU_CAPABILITY=avx2`` (torch's kernels, ``torch.backends.cpu.get_cpu_capability()``),
``MKL_ENABLE_INSTRUCTIONS=AVX2`` (MKL's: a batch-64 step's matrix products, 1.7x slower there),
``ONEDNN_MAX_CPU_ISA=AVX2`` and ``LP_NATIVE_VECTOR_WIDTH=256`` (Mesa's llvmpipe): how an AVX2 figure is measured
without an AVX2 machine (the line names the variables set).
"""

from __future__ import annotations

import os
import pathlib
import platform

import torch

# CPU flags that change which kernels run, in /proc/cpuinfo's spelling.
ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_tile")
EMULATION_VARIABLES = ("ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA",
                       "LP_NATIVE_VECTOR_WIDTH")


def _cpuinfo() -> list[str]:
    """``/proc/cpuinfo``'s lines (none where there is no such file: not Linux)."""
    path = pathlib.Path("/proc/cpuinfo")
    return path.read_text().splitlines() if path.is_file() else []


def cpu_model() -> str:
    """The CPU's model name (Linux), else what the platform says."""
    found = [line.partition(":")[2].strip() for line in _cpuinfo() if line.startswith("model name")]
    return found[0] if found else platform.processor() or platform.machine()


def cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux; empty elsewhere)."""
    found = [line.partition(":")[2].split() for line in _cpuinfo() if line.startswith("flags")]
    return set(found[0]) if found else set()


def machine_line() -> str:
    """One line naming the machine a figure was measured on: CPU, cores, ISA flags, torch's kernels and threads."""
    flags = cpu_flags()
    isa = "/".join(flag for flag in ISA_FLAGS if flag in flags) or "no AVX2"
    emulated = ", ".join(f"{name}={os.environ[name]}" for name in EMULATION_VARIABLES if name in os.environ)
    return (f"{cpu_model()}, {os.cpu_count()} cores, {isa}; torch {torch.__version__} kernels "
            f"{torch.backends.cpu.get_cpu_capability()}, {torch.get_num_threads()} threads"
            + (f" ({emulated})" if emulated else ""))
