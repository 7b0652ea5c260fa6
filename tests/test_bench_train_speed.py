"""``dust-rl bench train-speed``: every phase of a recipe timed by the run itself, the machine named."""

from __future__ import annotations

import json
import time

import pytest

from dust_rl.cli import main
from dust_rl.runtime.machine import machine_line
from dust_rl.runtime.phase_timer import PhaseTimer

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_phase_timer_sums_each_phase_over_its_repeats():
    timer = PhaseTimer()
    for _ in range(3):
        with timer("wait"):
            time.sleep(0.01)
    with pytest.raises(ValueError), timer("fails"):  # a phase that raises still counts its time
        raise ValueError
    summary = timer.summary()
    assert list(summary) == ["wait", "fails"] and summary["wait"]["count"] == 3
    assert summary["wait"]["seconds"] >= 0.03 and summary["wait"]["ms_each"] == pytest.approx(
        1000 * summary["wait"]["seconds"] / 3)


def test_the_machine_line_names_the_cpu_its_kernels_and_threads(monkeypatch):
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    line = machine_line()
    assert "cores" in line and " kernels " in line and "threads" in line and "ATEN_CPU_CAPABILITY=avx2" in line


def test_train_speed_times_every_phase_of_the_recipe(tmp_path, capsys):
    out = tmp_path / "speed"
    args = ["bench", "train-speed", "--out", str(out), "--demos", "1", "--steps", "4", "--image-size", "32",
            "--eval-episodes", "1", "--runtime.threads", "1", "--runtime.no-progress"]
    main(args)
    result = json.loads((out / "train_speed.json").read_text())
    phases = {row["phase"]: row for row in result["rows"]}
    assert {"collection", "encode dataset", "read-out frames", "read-out frame tokens", "read-out fit",
            "read-out estimates", "step: data",
            "step: forward", "step: backward", "step: optimizer", "checkpoint", "step: all parts",
            "closed-loop evaluation"} == set(phases)
    assert all(row["ms_each"] > 0 for row in phases.values())
    assert phases["step: all parts"]["ms_each"] == pytest.approx(
        sum(phases[f"step: {part}"]["ms_each"] for part in ("data", "forward", "backward", "optimizer")))
    assert f"Machine: {result['machine']}" in capsys.readouterr().out
    features = sorted((out / "data" / "features").glob("*.npy"))
    first_encoded = [path.stat().st_mtime_ns for path in features]
    main(args)  # again: the data is reused, the run and its caches made anew (so encoding is timed again)
    assert [path.stat().st_mtime_ns for path in features] != first_encoded
    assert "collection" not in {row["phase"] for row in json.loads((out / "train_speed.json").read_text())["rows"]}
