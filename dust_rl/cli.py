"""``dust-rl`` command line.

Bad input ends in one line, ``dust-rl: error: <what is wrong and what to do>`` (exit code 1;
argument syntax errors: 2): a :class:`~dust_rl.errors.UserError` (bad settings, unusable datasets,
a busy dataset folder, a diverged training run), a corrupt or unfitting checkpoint, or a file
system error. Any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import pathlib
import shlex
import sys

from dust_rl.errors import ConfigError, UserError


def _names(text: str) -> list[str]:
    """A comma-separated list of names (``--task``, ``--cameras``)."""
    return [name.strip() for name in text.split(",")]


def _tasks(robot: str, task: str) -> list[str]:
    """``--task``: ``all`` (the robot's suite), one name, or comma-separated names."""
    from dust_rl.envs import list_tasks

    if task == "all":
        try:
            return list_tasks(robot)
        except ValueError as err:  # unknown robot
            raise ConfigError(str(err)) from err
    return _names(task)


def _demo(args: argparse.Namespace) -> None:
    """Run the scripted expert in closed loop with cameras and save an MP4 per task."""
    from dust_rl.atomic_files import write_json_atomic
    from dust_rl.data.video import write_mp4
    from dust_rl.env_factory import check_tasks, make_env
    from dust_rl.errors import check_at_least
    from dust_rl.expert_rollouts import run_expert_episode

    out = pathlib.Path(args.out)
    tasks = _tasks(args.robot, args.task)
    check_at_least(args, 1, "episodes")
    check_at_least(args, 0, "seed")
    check_tasks(args.env, {}, tasks)
    summary = []
    for task in tasks:
        env = make_env(args.env, {"task": task, "image_size": args.image_size}).unwrapped
        frames, results = [], []
        for seed in range(args.seed, args.seed + args.episodes):
            result = run_expert_episode(env, seed, record=True)
            frames += result.frames
            results.append(result)
            print(f"{task} seed {seed}: success={result.success} steps={result.length} "
                  f"instruction={result.instruction!r}")
        video = out / f"{task}.mp4"
        write_mp4(video, frames, env.metadata["render_fps"], pad_odd=True)
        env.close()
        summary.append({"task": task, "episodes": len(results),
                        "successes": sum(r.success for r in results), "video": str(video)})
    write_json_atomic(out / "summary.json", summary, indent=2)
    for row in summary:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful; video: {row['video']}")
    print(f"summary: {out / 'summary.json'}")


def _expert_table(args: argparse.Namespace) -> None:
    """Measure every task's scripted expert over many seeds and print a markdown table."""
    from dust_rl.atomic_files import write_json_atomic, write_text_atomic
    from dust_rl.expert_rollouts import expert_success_table, format_table

    rows = expert_success_table(args.env, _tasks(args.robot, args.task), args.seeds)
    table = format_table(rows)
    print(table)
    if args.out:
        write_text_atomic(args.out, table + "\n")
        write_json_atomic(pathlib.Path(args.out).with_suffix(".json"), rows, indent=2)


def _collect(args: argparse.Namespace) -> None:
    """Collect scripted-expert demonstrations into a dataset folder (re-run the same command to resume)."""
    from dust_rl.data import DemoDataset, collect_demos
    from dust_rl.data.tools import dataset_summary

    tasks = _tasks(args.robot, args.task)
    env_kwargs = {"image_size": args.image_size}
    if args.cameras:
        env_kwargs["cameras"] = _names(args.cameras)
    if args.privileged_state:
        env_kwargs["privileged_state"] = True
    collect_demos(args.out, args.env, tasks, args.episodes, env_kwargs=env_kwargs, workers=args.workers,
                  start_seed=args.seed, noise_std=args.noise_std, keep_failed=args.keep_failed)
    print(dataset_summary(DemoDataset(args.out)))


def _dataset_info(args: argparse.Namespace) -> None:
    """Summarise a dataset: episodes, tasks, lengths, success, sizes."""
    from dust_rl.data import DemoDataset
    from dust_rl.data.tools import dataset_summary

    print(dataset_summary(DemoDataset(args.dir)))


def _dataset_video(args: argparse.Namespace) -> None:
    """Write an MP4 grid of a dataset's episodes."""
    from dust_rl.data import DemoDataset
    from dust_rl.data.tools import write_episode_grid
    from dust_rl.errors import check_at_least

    check_at_least(args, 1, "episodes", "columns")
    dataset = DemoDataset(args.dir)
    episodes = range(min(args.episodes, dataset.num_episodes))
    print(write_episode_grid(dataset, args.out, episodes, columns=args.columns))


def _dataset_export(args: argparse.Namespace) -> None:
    """Export a dataset to another format (LeRobotDataset v3.0)."""
    from dust_rl.data import DemoDataset
    from dust_rl.data.lerobot_export import export_lerobot

    if not 0 <= args.crf <= 51:
        raise ConfigError(f"crf must be in [0, 51] (H.264 quality), got {args.crf}")
    print(export_lerobot(DemoDataset(args.dir), args.out, crf=args.crf))


def _dataset_import(args: argparse.Namespace) -> None:
    """Import a LeRobotDataset v3.0 folder as a new dataset."""
    from dust_rl.data.lerobot_import import import_lerobot

    env_kwargs = {} if args.image_size is None else {"image_size": args.image_size}
    if args.cameras:
        env_kwargs["cameras"] = _names(args.cameras)
    import_lerobot(args.source, args.out, env_id=args.env, task=args.task, env_kwargs=env_kwargs)
    print(args.out)


def _pretrain_encoder(args: argparse.Namespace) -> None:
    """Pretrain the frozen image encoder (conv autoencoder) on dataset frames and write it to one file."""
    from dust_rl.agents import AutoencoderConfig
    from dust_rl.data import DemoDataset
    from dust_rl.pretrain_encoder import pretrain_encoder

    config = AutoencoderConfig(image_size=args.image_size, latent_grid=args.grid, dim=args.dim, width=args.width)
    report = pretrain_encoder([DemoDataset(d) for d in args.dataset], args.out, config, steps=args.steps,
                              batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                              command=args.command_line)
    heldout = "n/a" if report.heldout_loss is None else f"{report.heldout_loss:.5f}"
    print(f"{report.path}: {report.steps} steps in {report.seconds:.0f} s on {report.train_frames} frames; "
          f"pixel MSE train {report.train_loss:.5f}, held-out {heldout}")


def _encoder_check(args: argparse.Namespace) -> None:
    """Linear probes: how well each camera's frozen tokens give the objects' positions (probe.json, probe.png)."""
    from dust_rl.agents.backbone import resolve_image_encoder
    from dust_rl.data import DemoDataset
    from dust_rl.encoder_check import probe_dataset, write_encoder_check
    from dust_rl.errors import check_at_least

    check_at_least(args, 1, "every")
    dataset, encoder = DemoDataset(args.dataset), resolve_image_encoder(args.image_encoder)
    grid = tuple(args.grid) if args.grid else encoder.native_grid()
    results = probe_dataset(dataset, encoder, grid, every=args.every)
    title = f"{args.image_encoder or 'default encoder'}, {grid[0]}x{grid[1]} tokens, {dataset.root.name}"
    paths = write_encoder_check(results, pathlib.Path(args.out), title)
    for camera, result in results.items():
        values = " ".join(f"{v:.2f}" for v in result.r2.tolist())
        print(f"{camera}: held-out R^2 per environment-state column [{values}] (mean {result.r2.mean():.2f})")
    print(f"{paths['plot']}\n{paths['json']}")


def _add_dataset_commands(commands: argparse._SubParsersAction) -> None:
    dataset = commands.add_parser("dataset", help="inspect, export and import demonstration datasets")
    actions = dataset.add_subparsers(dest="action", required=True)
    info = actions.add_parser("info", help=_dataset_info.__doc__)
    info.add_argument("dir")
    info.set_defaults(func=_dataset_info)
    video = actions.add_parser("video", help=_dataset_video.__doc__)
    video.add_argument("dir")
    video.add_argument("--out", required=True, help="MP4 file")
    video.add_argument("--episodes", type=int, default=16, help="show the first N episodes")
    video.add_argument("--columns", type=int, default=4)
    video.set_defaults(func=_dataset_video)
    export = actions.add_parser("export", help=_dataset_export.__doc__)
    export.add_argument("dir")
    export.add_argument("--format", choices=["lerobot"], default="lerobot")
    export.add_argument("--out", required=True, help="new folder")
    export.add_argument("--crf", type=int, default=18, help="H.264 quality (0 = lossless luma, 18 = near-transparent)")
    export.set_defaults(func=_dataset_export)
    imp = actions.add_parser("import", help=_dataset_import.__doc__)
    imp.add_argument("source", help="LeRobotDataset v3.0 folder")
    imp.add_argument("--out", required=True, help="new dataset folder")
    imp.add_argument("--env", default=None, help="env the data was recorded in (needed without meta/dust_rl.json)")
    imp.add_argument("--task", default=None, help="the env task of every episode (with --env)")
    imp.add_argument("--image-size", type=int, default=None, help="env image size matching the videos (with --env)")
    imp.add_argument("--cameras", default=None, help="comma-separated env cameras matching the videos (with --env)")
    imp.set_defaults(func=_dataset_import)


# Commands configured by a dataclass, parsed by tyro: name -> (module, config class, runner, help).
TYRO_COMMANDS = {
    "train": ("dust_rl.train", "TrainConfig", "train_command",
              "train DUST (or a baseline) by imitation on a dataset (dust-rl train --help)"),
    "eval": ("dust_rl.evaluate", "EvalConfig", "evaluate_command",
             "evaluate a policy in closed loop and write a report (dust-rl eval --help)"),
    "finetune": ("dust_rl.finetune", "FinetuneConfig", "finetune_command",
                 "fine-tune a trained policy with RL (stable-baselines3), the policy itself frozen "
                 "(dust-rl finetune --help)"),
    "quickstart": ("dust_rl.quickstart", "QuickstartConfig", "quickstart",
                   "collect, train, evaluate and report on a small default: the README's main job"),
}


def _run_tyro_command(argv: list[str], command_line: str) -> None:
    import importlib

    import tyro

    module, config_class, runner, _ = TYRO_COMMANDS[argv[0]]
    module = importlib.import_module(module)
    config = tyro.cli(getattr(module, config_class), args=argv[1:], prog=f"dust-rl {argv[0]}")
    getattr(module, runner)(config, command_line)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dust-rl", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    for name, (*_, text) in TYRO_COMMANDS.items():  # listed here; their arguments are parsed by tyro
        commands.add_parser(name, help=text, add_help=False)

    demo = commands.add_parser("demo", help=_demo.__doc__)
    demo.add_argument("--env", default="DustFranka-v0")
    demo.add_argument("--robot", default="franka", help="suite used by --task all")
    demo.add_argument("--task", default="pick_place", help="task name or 'all'")
    demo.add_argument("--episodes", type=int, default=2)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--image-size", type=int, default=128)
    demo.add_argument("--out", default="runs/demo")
    demo.set_defaults(func=_demo)

    table = commands.add_parser("expert-table", help=_expert_table.__doc__)
    table.add_argument("--env", default="DustFranka-v0")
    table.add_argument("--robot", default="franka")
    table.add_argument("--task", default="all")
    table.add_argument("--seeds", type=int, default=50)
    table.add_argument("--out", default=None, help="also write the table (.md) and rows (.json) here")
    table.set_defaults(func=_expert_table)

    collect = commands.add_parser("collect", help=_collect.__doc__)
    collect.add_argument("--env", default="DustFranka-v0")
    collect.add_argument("--robot", default="franka", help="suite used by --task all")
    collect.add_argument("--task", default="pick_place", help="task name, comma-separated names, or 'all'")
    collect.add_argument("--episodes", type=int, default=100, help="successful episodes per task")
    collect.add_argument("--out", required=True, help="dataset folder (an existing one is resumed)")
    collect.add_argument("--workers", type=int, default=1, help="env processes")
    collect.add_argument("--seed", type=int, default=0, help="first episode seed of every task")
    collect.add_argument("--image-size", type=int, default=128)
    collect.add_argument("--cameras", default=None, help="comma-separated cameras (default: all of the robot's)")
    collect.add_argument("--noise-std", type=float, default=0.0,
                         help="DART: Gaussian noise on the executed action; the label stays the expert's")
    collect.add_argument("--keep-failed", action="store_true", help="also store failed episodes")
    collect.add_argument("--privileged-state", action="store_true",
                         help="append the objects' state to observation.state (an oracle: policies trained on it "
                              "need not see the objects; compare with an image-only dataset to measure perception)")
    collect.set_defaults(func=_collect)
    _add_dataset_commands(commands)

    pretrain = commands.add_parser("pretrain-encoder", help=_pretrain_encoder.__doc__)
    pretrain.add_argument("--dataset", action="append", required=True, help="dataset folder (repeat for several)")
    pretrain.add_argument("--out", required=True, help="encoder file (written atomically)")
    pretrain.add_argument("--steps", type=int, default=3000)
    pretrain.add_argument("--batch-size", type=int, default=64)
    pretrain.add_argument("--lr", type=float, default=2e-3)
    pretrain.add_argument("--seed", type=int, default=0)
    pretrain.add_argument("--image-size", type=int, default=128, help="frames are resized to this")
    pretrain.add_argument("--grid", type=int, default=4, help="latent token grid side")
    pretrain.add_argument("--dim", type=int, default=64, help="token size")
    pretrain.add_argument("--width", type=int, default=16, help="channels of the first conv stage")
    pretrain.set_defaults(func=_pretrain_encoder)

    encoder = commands.add_parser("encoder", help="diagnose frozen image encoders")
    encoder_actions = encoder.add_subparsers(dest="action", required=True)
    check = encoder_actions.add_parser("check", help=_encoder_check.__doc__)
    check.add_argument("--dataset", required=True, help="dataset folder (its rows hold the objects' positions)")
    check.add_argument("--image-encoder", default=None, help="encoder name or file (default: the policies' default)")
    check.add_argument("--grid", type=int, nargs=2, default=None, help="token grid (default: the encoder's own)")
    check.add_argument("--every", type=int, default=8, help="probe every n-th row")
    check.add_argument("--out", default="runs/encoder_check", help="folder for probe.json and probe.png")
    check.set_defaults(func=_encoder_check)
    return parser


def main(argv: list[str] | None = None) -> None:
    from dust_rl.agents.checkpoint_io import CheckpointError

    argv = sys.argv[1:] if argv is None else argv
    command_line = shlex.join(["dust-rl", *argv])  # provenance for files a command writes
    try:
        if argv and argv[0] in TYRO_COMMANDS:
            _run_tyro_command(argv, command_line)
            return
        args = build_parser().parse_args(argv)
        args.command_line = command_line
        args.func(args)
    except (UserError, CheckpointError, OSError) as err:
        raise SystemExit(f"dust-rl: error: {err}") from err


if __name__ == "__main__":
    main()
