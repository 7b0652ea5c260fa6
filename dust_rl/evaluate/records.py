"""What every closed-loop report records of its episodes, and the statistics it states of them.

An episode's fields are stored by name, so no reader depends on their order; :meth:`Episode.from_json` also reads
older reports' ``[seed, success, length, digest]`` (those kept under ``docs/results/``, a study's cached cells).

A success rate stands with its Wilson interval (the episode is the unit); two runs on the same episodes are compared
episode for episode (the exact McNemar test on the discordant ones); a claim about training stands with Student's t
interval over the training seeds (the seed is the unit a claim about training generalises over).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Hashable, Mapping, Sequence
from statistics import fmean, stdev

import torch

LIST_FIELDS = ("seed", "success", "length", "digest")  # the order of a list-shaped entry of an older report


@dataclasses.dataclass(frozen=True)
class Episode:
    """One evaluated episode; equal ``digest`` (:meth:`of`): same episode."""

    seed: int
    success: bool
    length: int
    digest: str

    @classmethod
    def of(cls, seed: int, success: bool, actions: torch.Tensor, final_state: torch.Tensor) -> Episode:
        """The record of an episode reset from ``seed`` that executed ``actions`` [T, Da] and ended in
        ``final_state``: its length counts env steps, however they were run (a torchrl rollout, an RL agent's env, a
        gymnasium loop), and its digest fingerprints the actions and the last state, so equal records mean the same
        episode."""
        data = actions.detach().cpu().contiguous().numpy().tobytes() + final_state.detach().cpu().numpy().tobytes()
        return cls(int(seed), bool(success), len(actions), hashlib.sha256(data).hexdigest()[:16])

    def to_json(self) -> dict:
        """The report's entry: each field by name."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, entry: Mapping | Sequence) -> Episode:
        """An entry as :meth:`to_json` writes it, or as a list of :data:`LIST_FIELDS` (an older report)."""
        return cls(**(entry if isinstance(entry, Mapping) else dict(zip(LIST_FIELDS, entry, strict=True))))


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a success rate (z = 1.96: 95%); (0, 1) when n = 0.

    Unlike the normal approximation it stays inside [0, 1] and is not empty at 0/n or n/n,
    which matters for the small episode counts of robot evaluations.
    """
    if n == 0:
        return 0.0, 1.0
    p, z2 = successes / n, z * z
    center = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, min(p, center - half)), min(1.0, max(p, center + half))  # rounding keeps 100 of 100 below 1


def mcnemar(arm: Mapping[Hashable, bool], reference: Mapping[Hashable, bool]) -> dict:
    """Over the episodes both have (same keys): those ``arm`` wins and ``reference`` loses (``gained``), the reverse
    (``lost``), and the exact two-sided McNemar p-value of that split of the discordant episodes."""
    keys = arm.keys() & reference.keys()
    gained = sum(arm[k] and not reference[k] for k in keys)
    lost = sum(reference[k] and not arm[k] for k in keys)
    n = gained + lost
    tail = sum(math.comb(n, k) for k in range(min(gained, lost) + 1)) / 2 ** n
    return {"gained": gained, "lost": lost, "p_value": min(1.0, 2 * tail)}


def paired_comparison(base: Sequence[Episode], other: Sequence[Episode]) -> dict:
    """How ``other`` differs from ``base`` on the same seeds: :func:`mcnemar` of their episodes by seed.

    Why: two policies run on the same seeds share each layout's difficulty, so the discordant episodes alone carry
    the difference; the test on them tells a gain from noise where two overlapping Wilson intervals cannot.

    Raises:
        ValueError: the two runs were not on the same seeds.
    """
    outcome = {e.seed: e.success for e in base}
    if sorted(outcome) != sorted(e.seed for e in other):
        raise ValueError("a paired comparison needs both runs on the same seeds")
    return mcnemar({e.seed: e.success for e in other}, outcome)


def paired(arm: Mapping[tuple, bool], reference: Mapping[tuple, bool]) -> dict:
    """``arm`` against ``reference`` over the episodes both have, keyed (task, training seed, evaluation seed's
    place): how many ``episodes`` were paired, :func:`mcnemar` of them, and each training seed's success difference
    (``seed_differences``) with the t-interval of their mean (``difference_ci95``): McNemar's p counts episodes, this
    interval counts training runs."""
    keys = arm.keys() & reference.keys()
    by_seed: dict[int, list[int]] = {}
    for task, seed, place in keys:
        by_seed.setdefault(seed, []).append(int(arm[task, seed, place]) - int(reference[task, seed, place]))
    differences = {str(seed): fmean(by_seed[seed]) for seed in sorted(by_seed)}
    return {"episodes": len(keys), **mcnemar(arm, reference), "seed_differences": differences,
            "difference_ci95": t_bounds(list(differences.values()))}


def t_bounds(values: Sequence[float], level: float = 0.95) -> list[float] | None:
    """Student's t interval of the mean of ``values``, one per training seed; None for fewer than two."""
    if len(values) < 2:
        return None
    mean = fmean(values)
    half = t_critical(len(values) - 1, level) * stdev(values) / math.sqrt(len(values))
    return [mean - half, mean + half]


def t_interval(rates: Sequence[float], level: float = 0.95) -> list[float] | None:
    """:func:`t_bounds` of success rates, clipped to [0, 1]."""
    bounds = t_bounds(rates, level)
    return None if bounds is None else [max(0.0, bounds[0]), min(1.0, bounds[1])]


def t_critical(df: int, level: float = 0.95) -> float:
    """The two-sided critical value of Student's t with ``df`` degrees of freedom (12.71 at 1, 4.30 at 2, towards
    1.96 as ``df`` grows, for 95%): bisection on the exact central probability of whole ``df``."""
    low, high = 0.0, 1e6
    while high - low > 1e-9 * high:
        mid = (low + high) / 2
        low, high = (mid, high) if _t_central(mid, df) < level else (low, mid)
    return high


def _t_central(t: float, df: int) -> float:
    """P(|T| < t) for Student's t with whole ``df`` degrees of freedom (Abramowitz & Stegun 26.7.3, 26.7.4)."""
    theta = math.atan(t / math.sqrt(df))
    c2, odd = math.cos(theta) ** 2, df % 2
    term, total = math.cos(theta) if odd else 1.0, 0.0
    for k in range((df - 1) // 2 if odd else df // 2):
        total += term
        term *= c2 * (2 * k + 1 + odd) / (2 * k + 2 + odd)
    return 2 / math.pi * (theta + math.sin(theta) * total) if odd else math.sin(theta) * total
