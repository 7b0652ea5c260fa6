"""Where a run's time goes: wall-clock seconds per named phase, summed over its repeats.

A training run that takes 2-2.5x the step time a benchmark measures loses it somewhere other than the trunk's
forward pass: drawing and gathering batches, the optimiser and weight average, checkpoints, periodic evaluations,
and the read-out's rendered frames before the first step. Each phase is timed where it runs (a ``with
timer("phase"):`` block), so the figures come from the run itself, not from a separate benchmark. On a CUDA device
the timer waits for the device at each block's end, or the phase that launched the kernels would look free and the
one that first reads a result would pay for them.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict
from collections.abc import Iterator

import torch


class PhaseTimer:
    """Seconds and repeats per phase.

    Args:
        device: where the timed work runs (a CUDA device is synchronised at each phase's end).
    """

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self.synchronize = torch.device(device).type == "cuda"
        self.seconds: dict[str, float] = defaultdict(float)
        self.count: dict[str, int] = defaultdict(int)

    @contextlib.contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            if self.synchronize:
                torch.cuda.synchronize()
            self.seconds[phase] += time.perf_counter() - start
            self.count[phase] += 1

    def summary(self) -> dict[str, dict[str, float]]:
        """Each phase's total seconds, repeats and mean milliseconds per repeat, in the order first timed."""
        return {phase: {"seconds": seconds, "count": self.count[phase],
                        "ms_each": 1000 * seconds / self.count[phase]} for phase, seconds in self.seconds.items()}
