"""The README's main job, ``dust-rl quickstart``: collect, train, evaluate, report, on a small default.

Every stage resumes: re-running the same command after an interruption skips
the demonstrations already on disk, continues training from the newest
checkpoint, and re-runs only the evaluation. The run folder ends up with

* ``data/``: the demonstrations (``dust-rl dataset info`` reads it);
* ``train/``: the training run (config, checkpoints, CSV/TensorBoard logs, ``policy.pt``, ``loss.png``);
* ``eval/``: ``report.md``, ``report.json``, ``success.png``, ``loss.png`` and rollout videos;
* ``quickstart.json``: the settings, the time each stage took, the overall success.

Every setting (and the image encoder file) is checked before the first demonstration is collected.
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass, field

from dust_rl.agents.encoders.backbone import check_image_encoder
from dust_rl.data import DemoDataset, collect_demos
from dust_rl.envs.factory import DEFAULT_ENV_ID
from dust_rl.errors import check_at_least
from dust_rl.evaluate.closed_loop import EvalConfig, eval_runtime, evaluate
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.recipes import RecipeName, vision_readout
from dust_rl.train.settings import NestedTrainSettings, TrainRuntime, as_class


@dataclass
class QuickstartConfig:
    """Collect expert demonstrations of one Franka task, train DUST on them, evaluate it in closed loop."""

    out: pathlib.Path = pathlib.Path("runs/quickstart")
    """Run folder (re-run the command to resume an interrupted run)."""
    task: str = "press_button"
    """Franka task (`dust_rl.envs.list_tasks("franka")`)."""
    demos: int = 200
    """Successful expert demonstrations to collect."""
    eval_episodes: int = 20
    """Closed-loop evaluation episodes."""
    workers: int = 1
    """Env processes for collection and evaluation (on 2 cores one is fastest: rendering uses both)."""
    image_size: int = 128
    """Camera resolution (every measured recipe ran at 128 px)."""
    runtime: TrainRuntime = field(default_factory=TrainRuntime)
    """Where and how training runs (`--runtime.threads`, `--runtime.device` ...); evaluation runs each worker on
    one thread at fp32 (`dust_rl.evaluate.closed_loop.eval_runtime`)."""
    recipe: RecipeName = "vision-readout"
    """The named recipe training starts from (`dust-rl train --help` lists them; `--train.*` flags override
    it)."""
    train: NestedTrainSettings = field(default_factory=lambda: as_class(NestedTrainSettings, vision_readout()))
    """Training (`--train.optim.steps`, `--train.model.variant` ...; as `dust-rl train`, defaults from
    `recipe`, runtime from `--runtime.*`)."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "demos", "eval_episodes", "workers", "image_size")


def quickstart(config: QuickstartConfig, command: str | None = None) -> dict:
    """Run the whole pipeline; returns the evaluation report."""
    began = time.perf_counter()
    data, train_dir, eval_dir = config.out / "data", config.out / "train", config.out / "eval"
    check_image_encoder(config.train.policy.image_encoder)
    train_config = TrainConfig.from_settings(config.train.under(config.runtime), dataset=data, out=train_dir,
                                             resume=(train_dir / "config.json").is_file(), recipe=config.recipe)
    eval_config = EvalConfig(policy=train_dir / "policy.pt", out=eval_dir, episodes=config.eval_episodes,
                             workers=config.workers, train_dir=train_dir,
                             runtime=eval_runtime(config.runtime))
    stages = {}

    tick = time.perf_counter()
    collect_demos(data, DEFAULT_ENV_ID, [config.task], config.demos, env_kwargs={"image_size": config.image_size},
                  workers=config.workers, progress=config.runtime.progress)
    stages["collect"] = time.perf_counter() - tick

    tick = time.perf_counter()
    result = train(train_config, command)
    stages["train"] = time.perf_counter() - tick

    tick = time.perf_counter()
    report = evaluate(eval_config, command)
    stages["eval"] = time.perf_counter() - tick
    stages["total"] = time.perf_counter() - began

    overall = report["overall"]
    print(f"\n{config.task}: {overall['successes']}/{overall['episodes']} successful "
          f"({100 * overall['success_rate']:.0f}%, 95% CI {100 * overall['ci95_low']:.0f}-"
          f"{100 * overall['ci95_high']:.0f}%) after {result.steps} training steps on "
          f"{DemoDataset(data).num_episodes} demonstrations")
    print("time: " + ", ".join(f"{name} {seconds / 60:.1f} min" for name, seconds in stages.items()))
    print(f"run folder: {config.out}\n  report: {eval_dir / 'report.md'}\n  plots: {eval_dir / 'success.png'}, "
          f"{eval_dir / 'loss.png'}\n  videos: {eval_dir / 'videos'}\n  policy: {result.policy}")
    summary = {"quickstart": config_json(config), "command": command,
               "stages_seconds": stages, "overall": overall, "report": str(eval_dir / "report.json")}
    write_json_atomic(config.out / "quickstart.json", summary, indent=2)
    return report
