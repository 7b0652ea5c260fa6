"""Validation success against training steps of several runs, one PNG: the curves a step count is chosen on.

Each run trained with ``dust-rl train ... --logging.eval-every N`` evaluates its averaged weights on validation seeds
(from ``--logging.eval-seed``, 5000) every N steps, each evaluation's report in ``eval/step-<N>/``; this draws their
success with the 95% Wilson intervals the reports give.

    .venv/bin/python experiments/validation_curves.py --runs runs/study/curve_dust_lam0.3 runs/study/curve_action_only \
        --out docs/results/2026-11-28-no-readout-study/validation_curves.png
"""

from __future__ import annotations

import argparse
import json
import pathlib

from matplotlib.figure import Figure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=pathlib.Path, nargs="+", required=True)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args()
    figure = Figure(figsize=(6, 4))
    axes = figure.subplots()
    for run in args.runs:
        paths = sorted(run.glob("eval/step-*/report.json"))  # step-<7 digits>: in step order
        steps = [int(path.parent.name.removeprefix("step-")) for path in paths]
        rows = [json.loads(path.read_text())["overall"] for path in paths]
        rates = [100 * row["success_rate"] for row in rows]
        axes.errorbar(steps, rates, yerr=[[rate - 100 * row["ci95_low"] for rate, row in zip(rates, rows)],
                                          [100 * row["ci95_high"] - rate for rate, row in zip(rates, rows)]],
                      marker="o", capsize=3, label=run.name)
        print(run.name, " ".join(f"{s}: {row['successes']}/{row['episodes']}" for s, row in zip(steps, rows)))
    axes.set(xlabel="training steps", ylabel="validation success, % (95% CI)", ylim=(0, 100))
    axes.legend()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(args.out, dpi=100)


if __name__ == "__main__":
    main()
