"""Where and how a command's torch work runs: :class:`RuntimeSettings`, the ``--runtime.*`` group every command
that runs a policy nests (``dust-rl train``, ``eval``, ``finetune``, ``collect --policy``, ``quickstart``, the
benchmarks and diagnoses).

One declaration, so ``--runtime.threads 1 --runtime.device cuda --runtime.no-progress`` mean the same in every
command, and a command that nests another's settings (``quickstart`` its training, ``finetune self-imitation`` its
rounds) hands its own group down instead of keeping two. A command with other defaults (one thread per evaluation
worker) builds the group with them (:func:`runtime_field`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from dust_rl.agents.model.precision import Precision
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.runtime.device import resolve_device


@dataclass(kw_only=True)
class RuntimeSettings:
    """Where and how the command's torch work runs (`--runtime.*`): results depend on it through `precision` and
    through the rounding of another device or of compiled kernels only."""

    threads: int | None = None
    """torch threads, per process (None: torch's choice)."""
    device: str = "auto"
    """Where the policy runs (`dust_rl.runtime.device`): auto (CUDA if present, else MPS, else CPU), cpu, cuda,
    cuda:N, mps. Envs, feature caches and saved policies stay on the CPU."""
    precision: Precision = "fp32"
    """The trunk's precision: fp32, or bf16 autocast (`dust_rl.agents.model.precision`; weights, optimiser and saved
    policies stay float32)."""
    compile: bool = False
    """Compile the trunk's forward pass with `torch.compile` (each process pays the compilation once; its cost on a
    2-core x86 CPU is in BENCHMARKS.md)."""
    progress: bool = True
    """Show progress bars."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "threads")
        resolve_device(self.device)

    def check_fp32(self, command: str) -> None:
        """Raise :class:`ConfigError` where ``command``, which runs its model at fp32 and uncompiled, is given
        another precision or compilation (so a flag is never silently ignored)."""
        given = [f"--runtime.{name}" for name in ("precision", "compile")
                 if getattr(self, name) != getattr(RuntimeSettings, name)]
        if given:
            raise ConfigError(f"{command} runs at fp32, uncompiled: drop {' and '.join(given)}")

    def at_fp32(self, **changes: object) -> RuntimeSettings:
        """These settings (a subclass's own fields dropped) at fp32 and uncompiled, with ``changes``: for the work a
        command runs beside its main job, whose results must not depend on the main job's precision."""
        return RuntimeSettings(**{"threads": self.threads, "device": self.device, "progress": self.progress,
                                  **changes})

    @property
    def thread_count(self) -> int:
        """The torch threads a process of the command runs with."""
        return self.threads or torch.get_num_threads()


def runtime_field(**defaults: object) -> RuntimeSettings:
    """A command's ``runtime`` field whose group starts from ``defaults`` (e.g. ``threads=1``)."""
    return field(default_factory=lambda: RuntimeSettings(**defaults))
