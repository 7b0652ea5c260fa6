"""``dust-rl`` command line."""

from __future__ import annotations

import argparse
import json
import pathlib

from dust_rl.envs import list_tasks


def _demo(args: argparse.Namespace) -> None:
    """Run the scripted expert in closed loop with cameras and save an MP4 per task."""
    import gymnasium as gym

    from dust_rl.expert_rollouts import run_expert_episode, write_video

    out = pathlib.Path(args.out)
    tasks = list_tasks(args.robot) if args.task == "all" else [args.task]
    summary = []
    for task in tasks:
        env = gym.make(args.env, task=task, image_size=args.image_size).unwrapped
        frames, results = [], []
        for seed in range(args.seed, args.seed + args.episodes):
            result = run_expert_episode(env, seed, record=True)
            frames += result.frames
            results.append(result)
            print(f"{task} seed {seed}: success={result.success} steps={result.length} "
                  f"instruction={result.instruction!r}")
        video = out / f"{task}.mp4"
        write_video(video, frames, fps=env.metadata["render_fps"])
        env.close()
        summary.append({"task": task, "episodes": len(results),
                        "successes": sum(r.success for r in results), "video": str(video)})
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    for row in summary:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful; video: {row['video']}")
    print(f"summary: {out / 'summary.json'}")


def _expert_table(args: argparse.Namespace) -> None:
    """Measure every task's scripted expert over many seeds and print a markdown table."""
    from dust_rl.expert_rollouts import expert_success_table, format_table

    tasks = list_tasks(args.robot) if args.task == "all" else [args.task]
    rows = expert_success_table(args.env, tasks, args.seeds)
    table = format_table(rows)
    print(table)
    if args.out:
        pathlib.Path(args.out).write_text(table + "\n")
        pathlib.Path(args.out).with_suffix(".json").write_text(json.dumps(rows, indent=2))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dust-rl", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

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
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
