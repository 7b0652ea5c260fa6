"""Demonstration collection speed and dataset size, as a markdown table.

Per backend and worker count: the demo collector's start-up (until its first
episode arrives; with Ray, starting the local cluster included) and its steady
throughput over the next ``--episodes`` episodes, collector only;
then one end-to-end ``collect_demos`` run (collector, episode writes,
consolidation) with one worker, whose consolidated memmap copy gives the disk
size per 1,000 transitions.

    python -m dust_rl.bench.collect_speed [--task pick_place] [--episodes 8] [--image-size 128] \
        [--workers 1 2] [--backends local ray]
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

from dust_rl.data import collect_demos
from dust_rl.data.collect import demo_collector
from dust_rl.data.tools import folder_size
from dust_rl.runtime.workers import Workers, ray_runtime


def collector_speed(task: str, image_size: int, workers: Workers, episodes: int) -> tuple[float, float]:
    """(start-up seconds, transitions per second over ``episodes`` episodes after the first)."""
    start = time.perf_counter()
    transitions = 0
    with (ray_runtime(workers),
          demo_collector("DustFranka-v0", {"task": task, "image_size": image_size}, workers) as collector):
        for count, trajectory in enumerate(collector):
            if count == 0:
                first = time.perf_counter()
            else:
                transitions += trajectory.shape[0]
            if count == episodes:
                break
    return first - start, transitions / (time.perf_counter() - first)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="pick_place")
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--backends", nargs="+", choices=["local", "ray"], default=["local"])
    args = parser.parse_args()
    lines = [f"`{args.task}` expert demos, {args.image_size}x{args.image_size} front + wrist cameras.", "",
             "| what | backend | workers | start-up (s) | transitions/s | MiB per 1000 transitions |",
             "|---|---|---|---|---|---|"]
    for backend in args.backends:
        for count in args.workers:
            startup, rate = collector_speed(args.task, args.image_size, Workers(count, backend), args.episodes)
            lines.append(f"| collector, steady | {backend} | {count} | {startup:.1f} | {rate:.0f} | |")
    with tempfile.TemporaryDirectory() as scratch:
        start = time.perf_counter()
        meta = collect_demos(scratch, tasks=[args.task], episodes=args.episodes,
                             env_kwargs={"image_size": args.image_size}, progress=False)
        seconds = time.perf_counter() - start
        data_bytes = folder_size(pathlib.Path(scratch, meta["data"]))
    lines.append(f"| collect_demos, end to end ({meta['num_rows']} transitions) | local | 1 | | "
                 f"{meta['num_rows'] / seconds:.0f} | {1000 * data_bytes / meta['num_rows'] / 2**20:.1f} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
