"""Validation success against training steps of several runs, one PNG: the curves a step count is chosen on.

Each run trained with ``dust-rl train ... --logging.eval-every N --logging.eval-episodes E`` logs the success of its
averaged weights on validation seeds (from ``--logging.eval-seed``, 5000) every N steps; this draws them with their
95% Wilson intervals.

    .venv/bin/python experiments/validation_curves.py --runs runs/study/curve_dust_lam0.3 runs/study/curve_action_only \
        --episodes 50 --out docs/results/2026-11-28-no-readout-study/validation_curves.png
"""

from __future__ import annotations

import argparse
import pathlib

from matplotlib.figure import Figure

from dust_rl.evaluate.closed_loop import wilson_interval


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=pathlib.Path, nargs="+", required=True)
    parser.add_argument("--episodes", type=int, required=True, help="episodes of each periodic evaluation")
    parser.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args()
    figure = Figure(figsize=(6, 4))
    axes = figure.subplots()
    for run in args.runs:
        rows = [line.split(",") for line in (run / "logs/train/scalars/eval/success_rate.csv").read_text().split()]
        steps, rates = [int(s) for s, _ in rows], [float(r) for _, r in rows]
        bounds = [wilson_interval(round(r * args.episodes), args.episodes) for r in rates]
        axes.errorbar(steps, [100 * r for r in rates], yerr=[[100 * (r - lo) for r, (lo, _) in zip(rates, bounds)],
                                                             [100 * (hi - r) for r, (_, hi) in zip(rates, bounds)]],
                      marker="o", capsize=3, label=run.name)
        print(run.name, " ".join(f"{s}: {100 * r:.0f}%" for s, r in zip(steps, rates)))
    axes.set(xlabel="training steps", ylabel=f"validation success, % ({args.episodes} episodes, 95% CI)", ylim=(0, 100))
    axes.legend()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(args.out, dpi=100)


if __name__ == "__main__":
    main()
