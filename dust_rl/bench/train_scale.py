"""Training throughput over 1 and N data-parallel processes, and the memory a run holds, as a markdown table.

Each row is a real ``dust-rl train`` run (``python -m dust_rl.train``) of ``--steps`` steps on ``--dataset``
into a scratch folder, sampled every 0.2 s through ``/proc`` (Linux): the peak of the processes' own
(anonymous) memory and of their file-backed resident pages (the memory-mapped feature cache and dataset,
which the OS can drop under pressure). Samples/s is the run's last logged ``train/samples_per_second``
(every process together). Encode the dataset's features once beforehand (any run with the same policy
settings) so that encoding is not timed.

    python -m dust_rl.bench.train_scale --dataset runs/data/pick_place [--nproc 1 2] [--steps 100] \\
        [-- --model.image-encoder efficientnet-lite0-s8 --model.cond-grid 8 8]
"""

from __future__ import annotations

import argparse
import csv
import pathlib
import subprocess
import sys
import tempfile
import time

from dust_rl.data import DemoDataset

MIB = 2**20


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (the spawned ranks)."""
    children = pathlib.Path(f"/proc/{pid}/task/{pid}/children")
    kids = [int(kid) for kid in children.read_text().split()] if children.exists() else []
    return [pid, *(grandchild for kid in kids for grandchild in process_tree(kid))]


def resident(pids: list[int]) -> tuple[int, int]:
    """(anonymous, file-backed) resident bytes of ``pids`` together."""
    anon = file = 0
    for pid in pids:
        try:
            fields = dict(line.split(":", 1) for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines())
        except (FileNotFoundError, ProcessLookupError):
            continue
        anon += int(fields.get("RssAnon", "0 kB").split()[0]) * 1024
        file += int(fields.get("RssFile", "0 kB").split()[0]) * 1024
    return anon, file


def run(dataset: pathlib.Path, nproc: int, steps: int, train_args: list[str]) -> dict[str, float]:
    """One training run: samples/s and the peak anonymous and file-backed resident MiB."""
    with tempfile.TemporaryDirectory() as scratch:
        out = pathlib.Path(scratch) / "run"
        command = [sys.executable, "-m", "dust_rl.train", "--recipe", "defaults", "--dataset", str(dataset),
                   "--out", str(out), "--optim.steps", str(steps), "--runtime.nproc", str(nproc),
                   "--logging.log-every", str(max(1, steps // 2)), "--logging.checkpoint-every", str(steps),
                   "--logging.loggers", "csv", "--runtime.no-progress", *train_args]
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
        peak_anon = peak_file = 0
        while process.poll() is None:
            anon, file = resident(process_tree(process.pid))
            peak_anon, peak_file = max(peak_anon, anon), max(peak_file, file)
            time.sleep(0.2)
        if process.returncode:
            raise SystemExit(f"training failed ({process.returncode}): {' '.join(command)}")
        with open(out / "logs" / "train" / "scalars" / "train" / "samples_per_second.csv") as file:
            speed = float(list(csv.reader(file))[-1][1])
    return {"samples_per_second": speed, "anon_mib": peak_anon / MIB, "file_mib": peak_file / MIB}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=pathlib.Path, required=True)
    parser.add_argument("--nproc", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("train_args", nargs="*", help="more `dust-rl train` arguments, after `--`")
    args = parser.parse_args()
    rows = DemoDataset(args.dataset).meta["num_rows"]
    caches = ", ".join(f"{path.stat().st_size / MIB:.0f}" for path in sorted((args.dataset / "features").glob("*.npy")))
    lines = [f"`dust-rl train` on `{args.dataset}` ({rows} rows; feature cache files there, MiB: {caches or 'none'}), "
             f"{args.steps} steps, {' '.join(args.train_args) or 'defaults'}.", "",
             "| processes | samples/s | peak anonymous memory (MiB) | peak file-backed resident (MiB) |",
             "|---|---|---|---|"]
    for nproc in args.nproc:
        row = run(args.dataset, nproc, args.steps, args.train_args)
        lines.append(f"| {nproc} | {row['samples_per_second']:.0f} | {row['anon_mib']:.0f} | {row['file_mib']:.0f} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
