"""docs/own_task.md works as written: its task file and launcher, then its commands (expert demo, collect, train,
eval) as the page gives them with only options that make them tiny added (the page's recipe and settings stand), in
one fresh interpreter (the registered task must not leak into this test process)."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys

from conftest import make_tiny_encoder
from test_docs_snippets import ROOT, code_blocks, shell_commands
from test_train import TINY_ARGS

from dust_rl.agents import save_image_encoder
from dust_rl.data import DemoDataset
from dust_rl.envs import list_tasks

PAGE = ROOT / "docs" / "own_task.md"
TASK, LAUNCHER = "reach_ball", "my_dust.py"
# What makes each of the page's commands tiny (counts, sizes, threads, progress bars), nothing that changes what
# they do; given after the page's own options, so these win. Training keeps the recipe the page's data picks
# (vision-readout), whose read-out scales down with the steps.
TINY = {
    "demo": ["--episodes", "1", "--image-size", "32"],
    "collect": ["--episodes", "2", "--image-size", "32"],
    "train": ["--optim.steps", "5", "--runtime.threads", "1", "--runtime.no-progress",
              "--model.image-encoder", "encoder.pt", "--model.cond-grid", "4", "4", "--model.readout-grid", "4", "4",
              *[arg for arg in TINY_ARGS if not arg.startswith("--recipe")]],
    "eval": ["--episodes", "1", "--workers", "1", "--videos", "0", "--runtime.no-progress"],
}
# Runs each command of the page through the launcher's main(), in one interpreter.
DRIVER = """
import sys
from my_dust import main, reach_ball
from dust_rl.envs import list_tasks
assert "reach_ball" in list_tasks("franka"), list_tasks("franka")
for line in sys.stdin.read().splitlines():
    main(line.split("\\0"))
"""


def test_the_page_registers_collects_trains_and_evaluates_its_task(tmp_path):
    for block in code_blocks(PAGE, "python"):  # each starts with the name of its file
        (tmp_path / block.code.splitlines()[0].removeprefix("# ")).write_text(block.code)
    save_image_encoder(make_tiny_encoder(), tmp_path / "encoder.pt")
    commands = [shlex.split(line) for block in code_blocks(PAGE, "bash") for line in shell_commands(block.code)]
    assert [c[:3] for c in commands] == [["python", LAUNCHER, name] for name in TINY]
    lines = "\n".join("\0".join([*command[2:], *TINY[command[2]]]) for command in commands)
    done = subprocess.run([sys.executable, "-c", DRIVER], input=lines, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300, env=os.environ | {"OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert TASK not in list_tasks("franka")  # registered in that interpreter only

    demo = json.loads((tmp_path / "runs/demo/reach_ball/summary.json").read_text())
    assert [(row["task"], row["successes"]) for row in demo] == [(TASK, 1)]
    dataset = DemoDataset(tmp_path / "runs/data/reach_ball")
    assert dataset.tasks == [TASK] and dataset.num_episodes == 2
    assert all(episode["success"] for episode in dataset.meta["episodes"])  # the expert solved every seed it kept
    assert [episode["seed"] for episode in dataset.meta["episodes"]] == [0, 1]  # ... and the first two it tried
    assert (tmp_path / "runs/train/reach_ball/policy.pt").is_file()
    trained = json.loads((tmp_path / "runs/train/reach_ball/config.json").read_text())["config"]
    assert (trained["recipe"], trained["readout"]["aux_frames"], trained["readout"]["warmup_steps"]) == (
        "vision-readout", 20, 10)  # as the page says: the read-out, at 5 of its 2,000 steps
    assert "read-out: 20 aux frames and 20 held out" in done.stdout
    report = json.loads((tmp_path / "runs/eval/reach_ball/report.json").read_text())
    assert [(row["task"], row["episodes"]) for row in report["tasks"]] == [(TASK, 1)]
