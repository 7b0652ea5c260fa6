"""The oracle-future test of every policy of a ``dust-rl bench suite`` study.

A study that finds DUST level with action_only must say why: whether its actions can read a future at all, and
what a better world model would buy them. :mod:`dust_rl.diagnose.world_model` answers both for one policy in
seconds; the suite runs it on every policy at its largest demo count, on expert episodes of the held-out seeds,
and puts one row per policy in ``results.md``. Reports are cached per episode count
(``diagnose/heldout_<n>/<cell>/``, the episodes in ``data/heldout_<n>/``), so another ``--diagnose-episodes``
diagnoses anew beside them, and a report that lacks a condition this version measures is redone.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Mapping

from dust_rl.diagnose.world_model import CONDITIONS, READINGS, WorldModelDiagnosis, diagnose
from dust_rl.runtime.settings import RuntimeSettings


def diagnosis_folder(out: pathlib.Path, kind: str, episodes: int) -> pathlib.Path:
    """Under a study's ``out``, the ``data`` (expert episodes) or ``diagnose`` (reports) folder of ``episodes``
    per task."""
    return out / kind / f"heldout_{episodes}"


def diagnose_policy(out: pathlib.Path, policy: pathlib.Path, dataset: pathlib.Path, runtime: RuntimeSettings,
                    command: str | None) -> dict:
    """The diagnosis report of ``policy`` on ``dataset`` in ``out`` (as read back from ``report.json``, whether run
    now or before) under the study's ``runtime`` at fp32, run unless a complete one is there."""
    if (report := finished_diagnosis(out)) is not None:
        return report
    diagnose(WorldModelDiagnosis(policy=policy, dataset=dataset, out=out,
                                 runtime=runtime.at_fp32()), command)
    return json.loads((out / "report.json").read_text())


def finished_diagnosis(out: pathlib.Path) -> dict | None:
    """The diagnosis report in ``out`` if one is there with every condition this version measures, else None."""
    report_path = out / "report.json"
    if not report_path.is_file():
        return None
    report = json.loads(report_path.read_text())
    oracle = report["oracle_future"]
    expected = set(CONDITIONS) if report.get("vision_stream") else {"own"}
    return report if set(oracle["conditions"]) | set(oracle["skipped"]) == expected else None


def diagnosis_rows(reports: Mapping[tuple[str, int], dict]) -> list[dict]:
    """Per diagnosed policy, keyed (arm label, training seed): each condition's action error, the paired
    differences that read the test (:data:`~dust_rl.diagnose.world_model.READINGS`), the conditions not run and
    why, and the world model's skill against the present frame (None without a vision stream)."""
    rows = []
    for (label, seed), report in reports.items():
        oracle, vision = report["oracle_future"], report.get("vision_stream")
        rows.append({"variant": label, "seed": seed, "windows": report["windows"],
                     "action_error": {name: row["action_error"]["mean"] for name, row in oracle["conditions"].items()},
                     "paired": {name: {"mean": row["mean"], "p": row["p"]}
                                for name, row in oracle["paired_action_error"].items() if name in READINGS},
                     "skipped": oracle["skipped"],
                     "skill": vision["joint_sample"]["skill"] if vision else None})
    return rows


def diagnosis_table(diagnosis: dict | None) -> list[str]:
    """Markdown lines of the oracle-future test of every diagnosed policy (none: no lines)."""
    if not diagnosis:
        return []

    def difference(row: dict, name: str) -> str:
        found = row["paired"].get(name)
        return "-" if found is None else f"{found['mean']:+.4f} ({found['p']:.3g})"

    lines = ["## The oracle-future test", "",
             f"Open-loop action error against the expert's chunks on {diagnosis['episodes']} expert episodes per task "
             f"from seed {diagnosis['first_seed']} on, with the vision stream holding "
             + "; ".join(f"{name}: {what}" for name, what in CONDITIONS.items())
             + " (`dust-rl diagnose world-model`; reports under `diagnose/`). true - noise below 0: the actions read "
             "a future; true - present below 0: a future, not only a second view of the present; own - true: what a "
             "better world model could buy them (p: paired over episodes); skill: the world model's joint sample "
             "against the present frame (1 - err / err_present).", "",
             "| variant | training seed | " + " | ".join(CONDITIONS) + " | "
             + " | ".join(f"{name} (p)" for name in READINGS) + " | world-model skill |",
             "|---|---|" + "---|" * (len(CONDITIONS) + len(READINGS) + 1)]
    notes = []
    for row in diagnosis["rows"]:
        skill = "-" if row["skill"] is None else f"{row['skill']:+.2f}"
        errors = [f"{row['action_error'][name]:.4f}" if name in row["action_error"] else "-" for name in CONDITIONS]
        lines.append(f"| {row['variant']} | {row['seed']} | " + " | ".join(errors) + " | "
                     + " | ".join(difference(row, name) for name in READINGS) + f" | {skill} |")
        notes += [f"{row['variant']}, seed {row['seed']}: {name} not run ({why})."
                  for name, why in row.get("skipped", {}).items()]
    return [*lines, "", *notes, *([""] if notes else [])]
