"""Where a recipe's time goes on this machine: collection, encoding, the read-out's frames and fit, each part of a
policy step, checkpoints and closed-loop evaluation, as a markdown table naming the CPU and its kernels.

It runs the real commands at a small scale: collects ``--demos`` expert demonstrations, trains the recipe scaled to
``--steps`` (:func:`~dust_rl.train.recipes.scaled_to_steps`: its read-out's frames and warm-up in proportion, so per
frame and per step they cost what the full recipe's do), whose own phase timer (``timing.json``,
:mod:`dust_rl.runtime.phase_timer`) gives the training rows, and evaluates the policy for ``--eval-episodes``.
Training starts anew each time (the run folder of an earlier benchmark is replaced; the collected data is kept
and reused), its feature and read-out caches cleared first so that encoding and rendering are timed. To time the
AVX2 code paths on an AVX-512 CPU, run it with ``ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2
ONEDNN_MAX_CPU_ISA=AVX2 LP_NATIVE_VECTOR_WIDTH=256`` (:mod:`dust_rl.runtime.machine`).

    dust-rl bench train-speed [--recipe vision-readout] [--task press_button] [--demos 10] [--steps 100]
"""

from __future__ import annotations

import json
import pathlib
import shutil
import time
from dataclasses import dataclass, replace

from dust_rl.data import DemoDataset, collect_demos
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.runtime.machine import machine_line
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.cache_files import CACHE_FOLDERS
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TIMING_FILE, TrainConfig, train
from dust_rl.train.readout.aux_frames import HELDOUT_FRAMES
from dust_rl.train.recipes import RECIPES, RecipeName, scaled_to_steps
from dust_rl.train.settings import LoggingSettings, train_runtime


@dataclass
class TrainSpeedConfig:
    """Time each phase of a recipe on this machine (`dust-rl bench train-speed`)."""

    out: pathlib.Path = pathlib.Path("runs/bench/train_speed")
    """Folder for the data, the training run and train_speed.md / train_speed.json."""
    recipe: RecipeName = "vision-readout"
    """The recipe timed (`dust-rl train --help` lists them)."""
    task: str = "press_button"
    """Franka task collected and trained on."""
    demos: int = 10
    """Expert demonstrations collected (and trained on)."""
    steps: int = 100
    """Policy steps; the recipe's read-out frames and warm-up steps scale with them."""
    eval_episodes: int = 2
    """Closed-loop episodes timed."""
    image_size: int = 128
    """Camera resolution (the recipes were measured at 128 px)."""
    runtime: RuntimeSettings = runtime_field(threads=2)
    """Where and how training and evaluation run (`--runtime.precision bf16` is fast only where the CPU has native
    bf16: AVX512-BF16 or AMX)."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "demos", "steps", "eval_episodes", "image_size")
        if self.steps > RECIPES[self.recipe].settings().optim.steps:
            raise ConfigError(f"--steps {self.steps} is more than recipe {self.recipe}'s own; time fewer steps")


def train_speed(config: TrainSpeedConfig) -> dict:
    """Collect, train and evaluate at the configured scale; returns the table's rows (also written as files)."""
    data, run = config.out / "data", config.out / "train"
    with torch_threads(config.runtime.thread_count):
        reused = (data / "meta.json").is_file()
        began = time.perf_counter()
        collect_demos(data, tasks=[config.task], episodes=config.demos, env_kwargs={"image_size": config.image_size},
                      progress=config.runtime.progress, wait_for_writer=True)
        collection = time.perf_counter() - began
        dataset = DemoDataset(data)
        for folder in CACHE_FOLDERS:  # encoding and rendering are what is timed
            shutil.rmtree(dataset.cache_root / folder, ignore_errors=True)
        if (run / "config.json").is_file():
            shutil.rmtree(run)
        settings = replace(scaled_to_steps(RECIPES[config.recipe].settings(), config.steps),
                           runtime=train_runtime(config.runtime),
                           logging=LoggingSettings(checkpoint_every=config.steps, loggers=("csv",)))
        train_config = TrainConfig.from_settings(settings, dataset=data, out=run, recipe=config.recipe)
        policy = train(train_config).policy
        report = evaluate(EvalConfig(policy=policy, out=config.out / "eval", episodes=config.eval_episodes,
                                     workers=1, videos=0, runtime=config.runtime))
    timing = json.loads((run / TIMING_FILE).read_text())
    rows = speed_rows(timing["phases"], train_config, len(dataset), None if reused else collection, report)
    result = {"machine": machine_line(), "config": config_json(config), "rows": rows}
    write_json_atomic(config.out / "train_speed.json", result)
    write_text_atomic(config.out / "train_speed.md", markdown(result))
    return result


def speed_rows(phases: dict[str, dict], config: TrainConfig, rows: int, collection_s: float | None,
               report: dict) -> list[dict]:
    """The table's rows: each phase's total seconds and its cost per unit of work (row, frame, step, env step);
    collection only where it ran (None: the data of an earlier benchmark was reused)."""
    frames = config.readout.aux_frames + (min(config.readout.aux_frames, HELDOUT_FRAMES)
                                          if config.readout.warmup_steps else 0)
    per = {"encode dataset": (rows, "row"), "read-out frames": (frames, "frame"),
           "read-out frame tokens": (frames, "frame"), "read-out fit": (config.readout.warmup_steps, "step"),
           "read-out estimates": (rows, "row")}
    table = [] if collection_s is None else [{"phase": "collection", "seconds": collection_s, "per": "row",
                                              "ms_each": 1000 * collection_s / rows}]
    for phase, row in phases.items():
        count, unit = per.get(phase, (row["count"], "step" if phase.startswith("step: ") else "call"))
        table.append({"phase": phase, "seconds": row["seconds"], "per": unit,
                      "ms_each": 1000 * row["seconds"] / max(count, 1)})
    steps = [row for row in table if row["phase"].startswith("step: ")]
    table.append({"phase": "step: all parts", "seconds": sum(r["seconds"] for r in steps), "per": "step",
                  "ms_each": sum(r["ms_each"] for r in steps)})
    table.append({"phase": "closed-loop evaluation", "seconds": report["episodes_time_s"], "per": "env step",
                  "ms_each": 1000 / report["env_steps_per_s"]})
    return table


def markdown(result: dict) -> str:
    config = result["config"]
    lines = [f"# Training speed: recipe {config['recipe']}, {config['task']}, {config['demos']} demonstrations, "
             f"{config['steps']} policy steps, {config['runtime']['precision']}", "",
             f"Machine: {result['machine']}", "",
             "| phase | total (s) | ms per | unit |", "|---|---|---|---|"]
    lines += [f"| {r['phase']} | {r['seconds']:.1f} | {r['ms_each']:.1f} | {r['per']} |" for r in result["rows"]]
    return "\n".join(lines) + "\n"


def train_speed_command(config: TrainSpeedConfig, command: str | None = None) -> None:
    """``dust-rl bench train-speed``: run, print the table, say where it is."""
    print(markdown(train_speed(config)))
    print(f"table: {config.out / 'train_speed.md'} (also train_speed.json)")
