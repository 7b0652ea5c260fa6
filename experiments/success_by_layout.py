"""Which layouts does a policy fail on? Success of evaluated episodes by where the named object starts.

Why: a success rate of 70% can hide a region of the table where the policy almost always fails, or a
cube rotation it cannot grasp; then more of the same training will not help, and the fix is there.
Every episode's layout follows from its seed, so it is rebuilt from an eval report's seeds alone (one
reset per episode, no policy run): the named object's start x (away from the robot base), y, and,
for a square target, how far the scripted expert's grasp turns the wrist from the radial direction
(the object's yaw under its 90-degree symmetry, `envs/tasks/grasping.py`). Each is cut into three
equal-count bins with the success and its 95% CI per bin. The first two columns of
``observation.environment_state`` must be the named object's xy (true of the Franka pick, place and
press tasks).

    .venv/bin/python experiments/success_by_layout.py runs/eval/RUN_seed5000/report.json \
        runs/eval/RUN_seed10000/report.json [--body target_cube]
"""

from __future__ import annotations

import argparse
import json
import pathlib

import gymnasium as gym
import numpy as np

import dust_rl  # noqa: F401 (registers the environments)
from dust_rl.envs.tasks.grasping import grasp_yaw
from dust_rl.evaluate.records import wilson_interval

BINS = 3


def layouts(report: dict, body: str) -> list[tuple[bool, float, float, float]]:
    """(success, x, y, |grasp turn| in degrees) per episode of one eval report (turn NaN without ``body``)."""
    rows = []
    for task in report["tasks"]:
        env = gym.make(report["env_id"], **{**report["env_kwargs"], "task": task["task"], "obs_mode": "state"})
        for seed, success, _length, _digest in task["per_episode"]:
            env.reset(seed=seed)
            base = env.unwrapped
            x, y = base.task.environment_state(base.data)[:2]
            turn = np.nan
            if body in {base.model.body(i).name for i in range(base.model.nbody)}:
                turn = abs(np.degrees(grasp_yaw(base.data, body) - (np.arctan2(y, x) + np.pi / 2)))
            rows.append((bool(success), float(x), float(y), float(turn)))
        env.close()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", help="report.json files of `dust-rl eval` (one env)")
    parser.add_argument("--body", default="target_cube", help="the square body the expert grasps")
    args = parser.parse_args()
    reports = [json.loads(pathlib.Path(path).read_text()) for path in args.reports]
    rows = np.array([row for report in reports for row in layouts(report, args.body)])
    success = rows[:, 0].astype(bool)
    print(f"{len(rows)} episodes, {int(success.sum())} successes\n")
    print("| quantity | bin | episodes | success | 95% CI |")
    print("|---|---|---|---|---|")
    for column, name in ((1, "x (m)"), (2, "y (m)"), (3, "grasp turn (deg)")):
        values = rows[:, column]
        if np.isnan(values).all():
            continue
        edges = np.quantile(values, np.linspace(0, 1, BINS + 1))
        for i in range(BINS):
            m = (values >= edges[i]) & ((values < edges[i + 1]) if i < BINS - 1 else (values <= edges[i + 1]))
            low, high = wilson_interval(int(success[m].sum()), int(m.sum()))
            print(f"| {name} | {edges[i]:.2f}-{edges[i + 1]:.2f} | {int(m.sum())} | "
                  f"{success[m].mean():.0%} | {low:.0%}-{high:.0%} |")


if __name__ == "__main__":
    main()
