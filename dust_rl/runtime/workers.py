"""Where episodes run: processes on this machine, or actors on a Ray cluster (``--workers``, ``--backend``).

Kept free of torch imports so the command line can declare these options cheaply; the collector that uses
them is :mod:`dust_rl.runtime.episode_collector`. Ray is an optional extra (``pip install "dust-rl[ray]"``).
"""

from __future__ import annotations

import contextlib
import importlib.util
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from dust_rl.errors import ConfigError, check_at_least

Backend = Literal["local", "ray"]

RAY_INSTALL_HINT = 'the ray backend needs Ray: pip install "dust-rl[ray]" (or: pip install ray==2.60.0)'


@dataclass(frozen=True)
class Workers:
    """How many workers run episodes, and where."""

    count: int = 1
    """Env processes (local) or Ray actors; 1 with the local backend runs in this process."""
    backend: Backend = "local"
    """local: processes on this machine; ray: actors on a Ray cluster."""
    threads: int = 1
    """Torch threads per worker (and CPUs each Ray actor reserves)."""
    ray_address: str | None = None
    """Ray cluster to join (`ray.init(address=...)`, e.g. `auto`); default: start a local one."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "count", "threads")
        if self.backend not in ("local", "ray"):
            raise ConfigError(f"unknown backend {self.backend!r}: choose local or ray")
        if self.ray_address is not None and self.backend != "ray":
            raise ConfigError("ray_address needs backend='ray'")
        if self.backend == "ray" and importlib.util.find_spec("ray") is None:
            raise ConfigError(RAY_INSTALL_HINT)


@contextlib.contextmanager
def ray_runtime(workers: Workers) -> Iterator[None]:
    """Keep one Ray runtime up for a whole command (every task's collector shares it); a no-op for local.

    A runtime started here is shut down at the end; one that was already up (or a joined cluster) is left as
    it was.
    """
    if workers.backend != "ray":
        yield
        return
    import ray

    started = not ray.is_initialized()
    if started:
        ray.init(address=workers.ray_address, include_dashboard=False, logging_level="warning",
                 log_to_driver=False)
    try:
        yield
    finally:
        if started:
            ray.shutdown()
