"""Which views does a policy act on? The same episodes with each camera's tokens replaced by the training mean.

The wrist camera sees an object at 1.3 mm per pixel from 10 cm where the front camera sees 7-11 mm
(docs/franka_results.md), but a policy may still steer by the front view alone; only closed-loop success tells.
``dust-rl diagnose cameras`` evaluates the policy as it is and then once per camera with that camera's frozen
tokens set to the training data's mean token (`EvalConfig.mean_cameras`), every arm on the same seeds, so each is
compared with the full policy episode by episode (exact McNemar on the discordant episodes).
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, replace

from dust_rl.agents import load_policy
from dust_rl.data.seeding import VALIDATION_SEED
from dust_rl.evaluate.closed_loop import WORKER_THREADS, EvalConfig, evaluate
from dust_rl.evaluate.records import Episode, mcnemar
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic

ALL_CAMERAS = "all cameras"  # the arm of the policy as it is, which every other arm is compared with


@dataclass
class CameraAblation:
    """Closed-loop success of a policy with each camera's tokens replaced by the training mean
    (`dust-rl diagnose cameras`)."""

    policy: pathlib.Path
    """Policy file (`dust-rl train`)."""
    out: pathlib.Path = pathlib.Path("runs/diagnose/cameras")
    """Folder for `report.json`, `report.md` and each arm's evaluation (`<arm>/report.json`)."""
    episodes: int = 50
    """Episodes per task and arm."""
    seed: int = VALIDATION_SEED
    """First episode seed of every arm (validation seeds by default: a choice made on them leaves the held-out
    seeds unseen)."""
    max_steps: int | None = None
    """Time limit per episode in env steps; default: the task's."""
    workers: int = 2
    """Env processes per evaluation."""
    runtime: RuntimeSettings = runtime_field(threads=WORKER_THREADS)
    """Where the policy runs, its threads per worker, precision, progress bars (as `dust-rl eval --runtime.*`)."""

    def __post_init__(self) -> None:
        self.evaluation()  # the same checks as dust-rl eval's, before any episode

    def evaluation(self) -> EvalConfig:
        """The evaluation every arm runs, but for its folder and its mean cameras."""
        return EvalConfig(policy=self.policy, episodes=self.episodes, seed=self.seed, max_steps=self.max_steps,
                          workers=self.workers, videos=0, runtime=self.runtime)


def diagnose_cameras(config: CameraAblation) -> dict:
    """Run every arm; returns (and writes) the table's rows."""
    cameras, base = load_policy(config.policy).cameras, config.evaluation()
    arms = {ALL_CAMERAS: (), **{f"{camera} as its mean": (camera,) for camera in cameras}}
    outcomes, rows = {}, []
    for name, mean_cameras in arms.items():
        folder = config.out / (name.split()[0] if mean_cameras else "all")
        report = evaluate(replace(base, out=folder, mean_cameras=mean_cameras))
        outcomes[name] = {(task["task"], episode.seed): episode.success for task in report["tasks"]
                          for episode in map(Episode.from_json, task["per_episode"])}
        overall = report["overall"]
        rows.append({"arm": name, "successes": overall["successes"], "episodes": overall["episodes"],
                     "success_rate": overall["success_rate"], "ci95": [overall["ci95_low"], overall["ci95_high"]],
                     "report": str(folder / "report.json")}
                    | ({"vs_all": mcnemar(outcomes[name], outcomes[ALL_CAMERAS])} if mean_cameras else {}))
    result = {"policy": str(config.policy), "seeds": [config.seed, config.seed + config.episodes - 1], "rows": rows}
    write_json_atomic(config.out / "report.json", result)
    write_text_atomic(config.out / "report.md", markdown(result))
    return result


def markdown(result: dict) -> str:
    lines = [f"# Camera ablation of {result['policy']}", "",
             f"Episode seeds {result['seeds'][0]}..{result['seeds'][1]} per task, the same for every arm.", "",
             "| arm | success | 95% CI | against all cameras: gained / lost (p) |", "|---|---|---|---|"]
    for row in result["rows"]:
        versus = row.get("vs_all")
        lines.append(f"| {row['arm']} | {row['success_rate']:.0%} ({row['successes']}/{row['episodes']}) | "
                     f"{row['ci95'][0]:.0%}-{row['ci95'][1]:.0%} | "
                     + (f"{versus['gained']} / {versus['lost']} ({versus['p_value']:.3g})" if versus else "-") + " |")
    return "\n".join(lines) + "\n"


def diagnose_cameras_command(config: CameraAblation, command: str | None = None) -> None:
    """``dust-rl diagnose cameras``: run, print the table, say where the files are."""
    diagnose_cameras(config)
    print((config.out / "report.md").read_text())
    print(f"report: {config.out / 'report.json'}")
