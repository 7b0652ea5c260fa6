"""The rows of a fine-tuning report: each policy on the same held-out seeds, compared with the base episode by episode.

Why: a fine-tuned policy and its base often differ by a few points, inside both Wilson intervals; the episodes one
wins and the other loses carry the difference (:func:`~dust_rl.evaluate.records.paired_comparison`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from dust_rl.evaluate.closed_loop import summary_row
from dust_rl.evaluate.records import Episode, paired_comparison

BASE_ROW = "base policy"  # the row a fine-tuning report compares every other row with, on the same seeds


def rows_against_base(episodes: Mapping[str, Sequence[Episode]]) -> list[dict]:
    """A summary row per named run (:func:`~dust_rl.evaluate.closed_loop.summary_row`), each but the
    :data:`BASE_ROW`'s with its paired comparison with the base (``vs_base``)."""
    return [summary_row(name, rows) | ({} if name == BASE_ROW else
                                       {"vs_base": paired_comparison(episodes[BASE_ROW], rows)})
            for name, rows in episodes.items()]
