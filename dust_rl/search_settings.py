"""The search expert's settings (:mod:`dust_rl.search_expert`), apart from it so the CLI declares them without
loading torch."""

from __future__ import annotations

import dataclasses
import math

from dust_rl.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class SearchSettings:
    """How the search expert chooses (:mod:`dust_rl.search_expert`); ``candidates = 1`` is the policy alone."""

    candidates: int = 1
    """Chunks the policy samples per plan, each tried in the simulator."""
    lookahead: int = 3
    """Chunks played per try before scoring: the candidate's, then the policy's own."""
    noise_scale: float = 1.0
    """The policy's initial noise while searching, in multiples of its trained noise (hotter samples differ more; on
    push and pick_place they won no more often, BENCHMARKS.md)."""

    def __post_init__(self) -> None:
        for name in ("candidates", "lookahead"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"search {name} must be an int >= 1, got {value!r}")
        if not (isinstance(self.noise_scale, (int, float)) and math.isfinite(self.noise_scale)
                and self.noise_scale > 0):
            raise ConfigError(f"search noise_scale must be a positive number, got {self.noise_scale!r}")

    @property
    def active(self) -> bool:
        return self.candidates > 1
