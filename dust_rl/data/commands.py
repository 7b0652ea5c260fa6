"""The data commands of ``dust-rl`` (demo, expert-table, collect, dataset): one dataclass of arguments per
command, and its runner.

Training, evaluation, fine-tuning and the quickstart keep their configs beside their code
(:mod:`dust_rl.train.imitation`, :mod:`dust_rl.train.encoder_commands`, :mod:`dust_rl.evaluate.closed_loop`,
:mod:`dust_rl.rl.finetune`, :mod:`dust_rl.quickstart`);
:mod:`dust_rl.cli` parses all of them with tyro. A task list is a name, comma-separated names or
``all``, the suite of the env's robot (the env id implies the robot).
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

from dust_rl.envs.factory import DEFAULT_ENV_ID, env_tasks
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.runtime.workers import Backend, Workers


@dataclass
class DemoCommand:
    """Run the scripted expert in closed loop with cameras and save an MP4 per task."""

    env: str = DEFAULT_ENV_ID
    """Gymnasium env id (its robot's suite is what `--task all` means)."""
    task: str = "pick_place"
    """Task name, comma-separated names, or `all`."""
    episodes: int = 2
    """Episodes per task."""
    seed: int = 0
    """Seed of the first episode."""
    image_size: int = 128
    """Camera resolution."""
    out: pathlib.Path = pathlib.Path("runs/demo")
    """Folder for one MP4 per task and summary.json."""


def run_demo(config: DemoCommand, command_line: str) -> None:
    from dust_rl.data.expert_rollouts import run_expert_episode
    from dust_rl.data.video import write_mp4
    from dust_rl.envs.factory import make_env
    from dust_rl.storage.atomic_files import write_json_atomic

    check_at_least(config, 1, "episodes")
    check_at_least(config, 0, "seed")
    summary = []
    for task in env_tasks(config.env, config.task):
        env = make_env(config.env, {"task": task, "image_size": config.image_size}).unwrapped
        frames, results = [], []
        for seed in range(config.seed, config.seed + config.episodes):
            result, strips = run_expert_episode(env, seed, with_frames=True)
            frames += strips
            results.append(result)
            print(f"{task} seed {seed}: success={result.success} steps={result.length} "
                  f"instruction={result.instruction!r}")
        video = config.out / f"{task}.mp4"
        write_mp4(video, frames, env.metadata["render_fps"], pad_odd=True)
        env.close()
        summary.append({"task": task, "episodes": len(results),
                        "successes": sum(r.success for r in results), "video": str(video)})
    write_json_atomic(config.out / "summary.json", summary, indent=2)
    for row in summary:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful; video: {row['video']}")
    print(f"summary: {config.out / 'summary.json'}")


@dataclass
class ExpertTableCommand:
    """Measure every task's scripted expert over many seeds and print a markdown table."""

    env: str = DEFAULT_ENV_ID
    """Gymnasium env id."""
    task: str = "all"
    """Task name, comma-separated names, or `all`."""
    episodes: int = 50
    """Episodes per task (seeds 0..N-1), as `--episodes` counts them in collect and eval."""
    out: pathlib.Path | None = None
    """Also write the table (.md) and rows (.json) here."""


def run_expert_table(config: ExpertTableCommand, command_line: str) -> None:
    from dust_rl.data.expert_rollouts import expert_success_table, format_table
    from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic

    check_at_least(config, 1, "episodes")
    rows = expert_success_table(config.env, env_tasks(config.env, config.task), config.episodes)
    table = format_table(rows)
    print(table)
    if config.out:
        write_text_atomic(config.out, table + "\n")
        write_json_atomic(config.out.with_suffix(".json"), rows, indent=2)


@dataclass
class CollectCommand:
    """Collect scripted-expert demonstrations (or a trained policy's rollouts) into a dataset folder (re-run the
    same command to resume)."""

    out: pathlib.Path
    """Dataset folder (an existing one is resumed)."""
    env: str = DEFAULT_ENV_ID
    """Gymnasium env id."""
    task: str = "pick_place"
    """Task name, comma-separated names, or `all`."""
    episodes: int = 100
    """Successful episodes per task."""
    workers: int = 1
    """Env processes (or Ray actors)."""
    backend: Backend = "local"
    """Where the workers run: processes on this machine, or actors on a Ray cluster (`pip install
    "dust-rl[ray]"`); same dataset either way."""
    ray_address: str | None = None
    """Ray cluster to join with `--backend ray` (e.g. `auto`); default: start a local one for the command."""
    seed: int = 0
    """First episode seed of every task."""
    image_size: int = 128
    """Camera resolution."""
    cameras: tuple[str, ...] = ()
    """Cameras to record (default: all of the robot's)."""
    noise_std: float = 0.0
    """DART: Gaussian noise on the executed action; the label stays the expert's."""
    keep_failed: bool = False
    """Also store failed episodes."""
    policy: pathlib.Path | None = None
    """A trained `policy.pt` to roll out instead of the scripted expert, as `dust-rl eval` runs it (its env
    settings must match `--image-size`...): rows keep its actions as `action` and the expert's as
    `expert_action`; `--episodes` counts its successes."""
    privileged_state: bool = False
    """Append the objects' state to observation.state: an oracle (policies trained on it need not see the
    objects; compare with an image-only dataset to measure what perception costs)."""
    runtime: RuntimeSettings = runtime_field(threads=1, device="cpu")
    """Where and how the rolled-out policy runs (with `--policy`: threads per worker, the CPU unless
    `--runtime.device` says otherwise), progress bars."""


def run_collect(config: CollectCommand, command_line: str) -> None:
    from dust_rl.data import DemoDataset, collect_demos
    from dust_rl.data.tools import dataset_summary

    env_kwargs: dict = {"image_size": config.image_size}
    if config.cameras:
        env_kwargs["cameras"] = list(config.cameras)
    if config.privileged_state:
        env_kwargs["privileged_state"] = True
    if config.policy is None:
        if config.runtime.device != "cpu":
            raise ConfigError("--runtime.device places a rolled-out policy (--policy); the scripted expert runs on "
                              "the CPU")
        config.runtime.check_fp32("dust-rl collect without --policy (the scripted expert)")
    workers = Workers(config.workers, config.backend, config.runtime.thread_count, config.ray_address)
    collect_demos(config.out, config.env, env_tasks(config.env, config.task), config.episodes,
                  env_kwargs=env_kwargs, workers=workers, start_seed=config.seed, noise_std=config.noise_std,
                  keep_failed=config.keep_failed, policy=config.policy, policy_runtime=config.runtime,
                  progress=config.runtime.progress)
    print(dataset_summary(DemoDataset(config.out)))


@dataclass
class DatasetInfo:
    """Summarise a dataset: episodes, tasks, lengths, success, sizes."""

    dir: tyro.conf.Positional[pathlib.Path]
    """Dataset folder."""

    def run(self) -> None:
        from dust_rl.data import DemoDataset
        from dust_rl.data.tools import dataset_summary

        print(dataset_summary(DemoDataset(self.dir)))


@dataclass
class DatasetVideo:
    """Write an MP4 grid of a dataset's episodes."""

    dir: tyro.conf.Positional[pathlib.Path]
    """Dataset folder."""
    out: pathlib.Path
    """MP4 file."""
    episodes: int = 16
    """Show the first N episodes."""
    columns: int = 4
    """Episodes side by side."""

    def run(self) -> None:
        from dust_rl.data import DemoDataset
        from dust_rl.data.tools import write_episode_grid

        check_at_least(self, 1, "episodes", "columns")
        if self.out.suffix.lower() != ".mp4":
            raise ConfigError(f"--out must name an .mp4 file (the grid is an H.264 MP4), got {self.out}")
        dataset = DemoDataset(self.dir)
        print(write_episode_grid(dataset, self.out, range(min(self.episodes, dataset.num_episodes)),
                                 columns=self.columns))


@dataclass
class DatasetExport:
    """Export a dataset to another format (LeRobotDataset v3.0)."""

    dir: tyro.conf.Positional[pathlib.Path]
    """Dataset folder."""
    out: pathlib.Path
    """New folder."""
    format: Literal["lerobot"] = "lerobot"
    """Target format."""
    crf: int = 18
    """H.264 quality (0 = lossless luma, 18 = near-transparent)."""

    def run(self) -> None:
        from dust_rl.data import DemoDataset
        from dust_rl.data.lerobot_export import export_lerobot

        if not 0 <= self.crf <= 51:
            raise ConfigError(f"crf must be in [0, 51] (H.264 quality), got {self.crf}")
        print(export_lerobot(DemoDataset(self.dir), self.out, crf=self.crf))


@dataclass
class DatasetImport:
    """Import a LeRobotDataset v3.0 folder as a new dataset."""

    source: tyro.conf.Positional[pathlib.Path]
    """LeRobotDataset v3.0 folder."""
    out: pathlib.Path
    """New dataset folder."""
    env: str | None = None
    """Env the data was recorded in (needed without meta/dust_rl.json)."""
    task: str | None = None
    """The env task of every episode (with --env)."""
    image_size: int | None = None
    """Env image size matching the videos (with --env)."""
    cameras: tuple[str, ...] = ()
    """Env cameras matching the videos (with --env)."""

    def run(self) -> None:
        from dust_rl.data.lerobot_import import import_lerobot

        env_kwargs: dict = {} if self.image_size is None else {"image_size": self.image_size}
        if self.cameras:
            env_kwargs["cameras"] = list(self.cameras)
        import_lerobot(self.source, self.out, env_id=self.env, task=self.task, env_kwargs=env_kwargs)
        print(self.out)


@dataclass
class DatasetCommand:
    """Inspect, export and import demonstration datasets."""

    action: (Annotated[DatasetInfo, tyro.conf.subcommand("info")]
             | Annotated[DatasetVideo, tyro.conf.subcommand("video")]
             | Annotated[DatasetExport, tyro.conf.subcommand("export")]
             | Annotated[DatasetImport, tyro.conf.subcommand("import")])
    """What to do with the dataset."""


def run_dataset(config: DatasetCommand, command_line: str) -> None:
    config.action.run()
