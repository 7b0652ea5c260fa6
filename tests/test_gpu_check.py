"""``dust-rl bench gpu`` at its tiny size on the CPU: every section runs, and a resumed run ends where an
uninterrupted one does."""

from __future__ import annotations

import json

import pytest

from dust_rl.bench.gpu_check import CheckFailedError, GpuCheckConfig, gpu_check_command
from dust_rl.cli import main
from dust_rl.runtime.settings import RuntimeSettings


def test_every_section_runs_and_resume_matches(tmp_path, capsys):
    out = tmp_path / "check"
    main(["bench", "gpu", "--size", "tiny", "--runtime.device", "cpu", "--out", str(out), "--runtime.no-progress"])
    results = json.loads((out / "results.json").read_text())
    rows = results["rows"]
    assert {row["section"] for row in rows} == {"train", "latency", "ddp", "eval"}
    assert [row for row in rows if row["status"] != "ok"] == []
    resume = next(row for row in rows if row["name"].startswith("resume"))
    # On the CPU a run cut back to its first checkpoint and resumed ends with the same weights, bit for bit.
    assert resume["detail"].endswith("uninterrupted run: 0")
    assert (out / "table.md").read_text() in capsys.readouterr().out


def test_failing_row_is_reported_and_the_rest_runs(tmp_path):
    out = tmp_path / "check"
    with pytest.raises(CheckFailedError, match="eval"):  # eval needs the policy the skipped ddp section trains
        gpu_check_command(GpuCheckConfig(out=out, size="tiny", sections=("eval", "latency"),
                                         runtime=RuntimeSettings(device="cpu", progress=False)))
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [row["status"] for row in rows] == ["failed"] + ["ok"] * (len(rows) - 1) and len(rows) > 1
    assert "ddp section trains the policy" in rows[0]["detail"]


def test_spent_budget_skips_rows(tmp_path):
    gpu_check_command(GpuCheckConfig(out=tmp_path, size="tiny", sections=("latency",), budget_s=0,
                                     runtime=RuntimeSettings(device="cpu", progress=False)))
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert rows and all(row["status"] == "skipped" for row in rows)
