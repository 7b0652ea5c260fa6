"""Which finished episodes make up the dataset: the first N successes by seed.

Defining the dataset by seeds (not by which worker finished first) makes it the
same whatever the number of workers or interruptions: for each task it holds the
first ``episodes`` seeds from ``start_seed`` whose episode succeeded (plus the
failed ones in between when failures are kept).
"""

from __future__ import annotations

from .episodes import EpisodeRecord


def select_episodes(records: dict[int, EpisodeRecord], start_seed: int, episodes: int,
                    keep_failed: bool) -> list[EpisodeRecord] | None:
    """The dataset's episodes of one task in seed order, or None while a needed seed is unknown."""
    selected: list[EpisodeRecord] = []
    successes, seed = 0, start_seed
    while successes < episodes:
        record = records.get(seed)
        if record is None:
            return None
        successes += record.success
        if record.success or (keep_failed and record.kept):
            selected.append(record)
        seed += 1
    return selected
