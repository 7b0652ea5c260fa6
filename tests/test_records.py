"""Episode records read by name, also from the list-shaped entries of older reports; the statistics recomputed from
kept reports give the numbers those reports state, to the last bit."""

from __future__ import annotations

import json
import pathlib

import pytest

from dust_rl.bench.suite import compare
from dust_rl.evaluate.closed_loop import summary_row
from dust_rl.evaluate.records import Episode, t_interval, wilson_interval

RESULTS = pathlib.Path(__file__).parents[1] / "docs" / "results"
KEPT_EVAL = RESULTS / "2026-12-01-train-speed" / "quickstart_avx512_report.json"  # `dust-rl eval`, 20/20
KEPT_STUDY = RESULTS / "2026-11-28-no-readout-study" / "pb200_results.json"  # `dust-rl bench suite`, 3 seeds


def test_an_older_reports_list_entry_reads_by_name():
    old = json.loads('[10000, true, 15, "8ee6cb8390f0c858"]')  # the first episode of KEPT_EVAL, as it stands
    episode = Episode.from_json(old)
    assert (episode.seed, episode.success, episode.length, episode.digest) == (10000, True, 15, "8ee6cb8390f0c858")
    assert episode.to_json() == {"seed": 10000, "success": True, "length": 15, "digest": "8ee6cb8390f0c858"}
    assert Episode.from_json(episode.to_json()) == episode
    with pytest.raises(ValueError):
        Episode.from_json([10000, True, 15])


def test_a_kept_eval_reports_rows_recompute_from_its_episodes():
    report = json.loads(KEPT_EVAL.read_text())
    (row,) = report["tasks"]
    episodes = [Episode.from_json(e) for e in row["per_episode"]]
    assert wilson_interval(20, 20) == (0.8388698745050667, 1.0) == (row["ci95_low"], row["ci95_high"])
    assert {k: row[k] for k in summary_row(row["task"], episodes)} == summary_row(row["task"], episodes)
    assert report["overall"] == summary_row("overall", episodes)
    assert report["env_steps"] == sum(e.length for e in episodes)


def test_a_kept_studys_intervals_and_paired_comparisons_recompute_from_its_rows():
    study = json.loads(KEPT_STUDY.read_text())
    for row in study["rows"]:
        assert t_interval(row["per_seed"]) == row["seed_ci95"]
        assert wilson_interval(row["successes"], row["episodes"]) == (row["ci95_low"], row["ci95_high"])
    assert compare(study["rows"], None) == study["comparisons"]
    first = study["comparisons"][0]  # dust against action_only: the study's headline
    assert (first["gained"], first["lost"], first["p_value"]) == (31, 16, 0.03998605682605216)
    assert first["difference_ci95"] == [-0.07913371791534314, 0.27913371791534314]
