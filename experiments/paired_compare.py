"""Compare evaluations of several policies with a base, episode for episode on the same seeds.

Why: a fine-tuned policy and its base, evaluated on the same 50 seeds, often differ by a few points, inside both
Wilson intervals. The episodes one wins and the other loses carry the whole difference; the exact McNemar test on
them (:func:`dust_rl.evaluate.records.paired_comparison`, also in every ``dust-rl finetune`` report) says
whether it is more
than noise.

    .venv/bin/python experiments/paired_compare.py --base runs/eval/B/report.json --others runs/eval/X/report.json ...

A comma-joined list of reports (``--base B1/report.json,B2/report.json``) pools their episodes, e.g. validation and
held-out seeds of the same policy; each other policy's list must cover the same seeds.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from dust_rl.evaluate.records import Episode, paired_comparison


def episodes(reports: str) -> dict[str, list[Episode]]:
    """Each task's episodes of comma-joined ``dust-rl eval`` reports, pooled in their order."""
    pooled: dict[str, list[Episode]] = {}
    for report in reports.split(","):
        for row in json.loads(pathlib.Path(report).read_text())["tasks"]:
            pooled.setdefault(row["task"], []).extend(map(Episode.from_json, row["per_episode"]))
    return pooled


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="the base policy's report.json (comma-joined: pooled)")
    parser.add_argument("--others", nargs="+", required=True, help="report.json files to compare (each comma-joined: "
                        "pooled)")
    args = parser.parse_args()
    base = episodes(args.base)
    for path in args.others:
        for task, rows in episodes(path).items():
            paired = paired_comparison(base[task], rows)
            print(f"{path} {task}: {sum(e.success for e in rows)}/{len(rows)} against the base's "
                  f"{sum(e.success for e in base[task])}; won {paired['gained']} the base lost, lost {paired['lost']} "
                  f"it won (McNemar p = {paired['p_value']:.3f})")


if __name__ == "__main__":
    main()
