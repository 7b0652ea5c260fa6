"""Success against demonstrations, one line per variant, from several `dust-rl bench suite` folders.

Why: each demonstration count of the study lives in a folder of its own (and the lambda_WM = 0 control in
another), so no single ``results.png`` shows how the variants scale. This reads every folder's ``results.json``,
keeps the rows sampled as trained, and draws success (episodes pooled over training seeds, 95% interval) against
demonstrations; a folder trained with ``--train.model.lambda-wm 0`` gets its own line, named so.

    .venv/bin/python experiments/data_scaling_plot.py runs/bench/press_button runs/bench/press_button_20 \
        runs/bench/press_button_100 runs/bench/press_button_20_wm0 runs/bench/press_button_100_wm0 \
        --out runs/bench/press_button_data_scaling.png
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib

from matplotlib.figure import Figure

from dust_rl.bench.suite import AS_TRAINED, percent_with_errors
from dust_rl.evaluate.report import save_png


def load(folder: pathlib.Path) -> dict:
    """A study folder's ``results.json``."""
    path = folder / "results.json"
    if not path.is_file():
        raise SystemExit(f"{folder}: no results.json; run `dust-rl bench suite --out {folder}` first")
    return json.loads(path.read_text())


def series(studies: dict[pathlib.Path, dict], variants: list[str]) -> dict[str, list[dict]]:
    """Rows of ``variants`` sampled as trained, by line name, sorted by demonstrations; one row per (line, demos)."""
    lines: dict[str, dict[int, dict]] = collections.defaultdict(dict)
    for folder, results in studies.items():
        no_world_model = results["train"]["policy"]["lambda_wm"] == 0
        for row in results["rows"]:
            if row["sampler"] != AS_TRAINED or row["variant"] not in variants:
                continue
            name = f"{row['variant']}, lambda_WM = 0" if no_world_model else row["variant"]
            if row["demos"] in lines[name]:
                raise SystemExit(f"{folder}: a second '{name}' row at {row['demos']} demonstrations; "
                                 "give each study's folder once")
            lines[name][row["demos"]] = row
    return {name: [by_demos[d] for d in sorted(by_demos)] for name, by_demos in sorted(lines.items())}


def plot(lines: dict[str, list[dict]], task: str, out_png: pathlib.Path) -> None:
    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    ax = fig.add_subplot()
    for name, rows in lines.items():
        demos = [r["demos"] for r in rows]
        rates, errors = percent_with_errors(rows)
        seeds = max(len(r["seeds"]) for r in rows)
        ax.errorbar(demos, rates, yerr=errors, capsize=3, marker="o", label=f"{name} (up to {seeds} seeds)")
    ax.set_xscale("log")
    every_demos = sorted({r["demos"] for rows in lines.values() for r in rows})
    ax.set_xticks(every_demos, [str(d) for d in every_demos])
    ax.minorticks_off()
    ax.set_xlabel("demonstrations")
    ax.set_ylabel("success on held-out seeds (%)")
    ax.set_ylim(0, 100)
    ax.set_title(f"{task}: success against demonstrations (95% intervals)")
    ax.legend(fontsize=8)
    save_png(fig, out_png)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", type=pathlib.Path, nargs="+", help="bench suite --out folders")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="PNG to write")
    parser.add_argument("--variants", nargs="+", default=["dust", "action_only"], help="variants to draw")
    args = parser.parse_args()
    studies = {folder: load(folder) for folder in args.folders}
    tasks = {results["task"] for results in studies.values()}
    if len(tasks) > 1:
        raise SystemExit(f"folders of different tasks {sorted(tasks)}: plot one task at a time")
    lines = series(studies, args.variants)
    plot(lines, tasks.pop(), args.out)
    for name, rows in lines.items():
        print(name + ": " + ", ".join(f"{r['demos']}: {100 * r['success_rate']:.0f}% ({r['successes']}/"
                                      f"{r['episodes']})" for r in rows))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
