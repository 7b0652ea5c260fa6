"""GPU readiness check, ``dust-rl bench gpu``: every path a GPU user takes, run and timed in one table.

Why one prepared command: a GPU is often lent for minutes, so the check must run start to end in one call,
keep going past a failing row (its error becomes the row), and stop starting rows once its time budget is
spent. At ``--size tiny`` it runs on the CPU in the test suite (``tests/test_gpu_check.py``), so it keeps
working between the times a GPU is at hand.

* **train**: one training step of the trunk (forward, backward, AdamW) on random stand-ins for cached
  features; presets ``cpu-small`` and ``gpu-base``, fp32 and bf16 autocast, batch 64 and the largest batch
  that fits (doubled until out of memory). Samples/s and peak device memory.
* **latency**: ``DustModel.predict_action`` for DUST (N_A = 4, N_o = 4 / 16 / 32) and action-only, batch 1
  and 32. Milliseconds per chunk.
* **ddp**: ``dust-rl collect`` (scripted expert), ``torchrun --nproc-per-node 1 -m dust_rl.train`` (NCCL on
  CUDA, gloo on the CPU), then the run cut back to its first checkpoint and resumed; on a GPU, also resumed
  on the CPU with CUDA hidden. Seconds, and the resumed weights' largest difference from the uninterrupted run's.
* **eval**: ``dust-rl eval`` of that policy with MuJoCo rendering (EGL where a GPU is). Episodes/s, env
  steps/s.
* **compile**: the training rows at batch 64 under ``torch.compile``; the first step's seconds are the
  compilation's.

Files: ``<out>/results.json`` (every row) and ``<out>/table.md`` (the printed table), written atomically.
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import json
import os
import pathlib
import platform
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Literal

import torch

from dust_rl.agents import DustConfig, DustModel, random_batch, schedule_for
from dust_rl.agents.config import POLICY_PRESETS
from dust_rl.agents.model.precision import Precision, autocast
from dust_rl.errors import UserError
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.config_json import config_json

Section = Literal["train", "latency", "ddp", "eval", "compile"]
PRECISIONS: tuple[Precision, ...] = ("fp32", "bf16")
N_COND_TOKENS = 40  # instruction tokens plus two cameras' 4x4 grids: the default policy's condition length
TASK = "press_button"


@dataclass(frozen=True)
class CheckSize:
    """How much one run of the check does."""

    presets: tuple[str, ...]
    batch: int
    max_batch: int
    steps: int
    latency_batches: tuple[int, ...]
    repeats: int
    compile: bool
    episodes: int
    train_steps: int
    train_batch: int
    eval_max_steps: int | None


SIZES = {
    "full": CheckSize(presets=("cpu-small", "gpu-base"), batch=64, max_batch=1 << 15, steps=10,
                      latency_batches=(1, 32), repeats=20, compile=True, episodes=5, train_steps=40, train_batch=64,
                      eval_max_steps=None),
    # The CPU test: every code path once, in under a minute on 2 cores (no compilation, few steps, tiny batches).
    "tiny": CheckSize(presets=("cpu-small",), batch=4, max_batch=8, steps=1, latency_batches=(1,), repeats=1,
                      compile=False, episodes=1, train_steps=4, train_batch=4, eval_max_steps=16),
}


@dataclass
class GpuCheckConfig:
    """Check that training, sampling, data-parallel training with resume and closed-loop evaluation run on a
    device, and time them: one table (`dust-rl bench gpu`)."""

    out: pathlib.Path = pathlib.Path("runs/gpu_check")
    """Folder for the dataset, run, evaluation and the result files (`results.json`, `table.md`)."""
    size: Literal["full", "tiny"] = "full"
    """`full`: the table's sizes (minutes on one GPU); `tiny`: every path once at toy sizes (the CPU test)."""
    sections: tuple[Section, ...] = ("train", "latency", "ddp", "eval", "compile")
    """Which parts to run (`eval` evaluates the policy `ddp` trains)."""
    text_encoder: pathlib.Path | None = None
    """Text model folder for the `ddp` policy (`--model.text-encoder`); None: the bundled MiniLM."""
    budget_s: float = 420.0
    """Rows not started within this many seconds are skipped (listed as such), so the check ends in time."""
    runtime: RuntimeSettings = runtime_field()
    """The device checked (`--runtime.device`), torch threads, whether each row is printed as it is measured; the
    sections time both precisions and compilation themselves."""

    def __post_init__(self) -> None:
        self.runtime.check_fp32("dust-rl bench gpu")


@dataclass
class Row:
    """One measured line of the table."""

    section: str
    name: str
    value: str
    detail: str = ""
    status: Literal["ok", "failed", "skipped"] = "ok"


class CheckFailedError(UserError):
    """Some rows of the check failed (their errors are in the table and ``results.json``)."""


def sync(device: torch.device) -> None:
    """Wait for the device's queued work, so wall clocks time it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed_s(fn: Callable[[], object], device: torch.device, repeats: int, warmup: int) -> list[float]:
    """Wall seconds of ``repeats`` calls after ``warmup`` calls, each ended by a device sync."""
    for _ in range(warmup):
        fn()
    sync(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return times


def _device_batch(config: DustConfig, batch_size: int, device: torch.device):
    """Random cached-feature stand-ins on ``device``: at most 256 distinct rows, repeated (the values do not
    change the speed, and drawing millions of rows on the CPU would take longer than the steps)."""
    distinct = random_batch(config, min(batch_size, 256), N_COND_TOKENS, torch.Generator().manual_seed(0))
    repeats = -(-batch_size // distinct.batch_size[0])
    return torch.cat([distinct.to(device)] * repeats)[:batch_size]


def _is_out_of_memory(err: BaseException) -> bool:
    return isinstance(err, torch.OutOfMemoryError) or "out of memory" in str(err).lower()


def _free(device: torch.device) -> None:
    if device.type == "cuda" and torch.cuda.is_initialized():  # rows that ran only child processes have none
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None


class _Trainer:
    """One preset's trunk with its optimiser on ``device``: a training step at any batch size."""

    def __init__(self, preset: str, device: torch.device, precision: Precision, compile_model: bool) -> None:
        torch.manual_seed(0)
        self.config = DustConfig(**POLICY_PRESETS[preset].model_settings(), cond_dim=POLICY_PRESETS[preset].d_model)
        self.model = DustModel(self.config).to(device).train()
        if compile_model:
            self.model.compile()
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=1e-4, fused=True)
        self.device, self.precision = device, precision
        self.generator = torch.Generator().manual_seed(0)
        self.params = sum(p.numel() for p in self.model.parameters())

    def steps_per_s(self, batch_size: int, steps: int, warmup: int) -> tuple[float, float]:
        """Samples/s (median step) and the first step's seconds (with ``torch.compile``, the compilation)."""
        batch = _device_batch(self.config, batch_size, self.device)

        def step() -> None:
            with autocast(self.device, self.precision):
                loss = self.model.compute_loss(batch, self.generator)["loss"]
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()

        first = timed_s(step, self.device, 1, 0)[0]
        return batch_size / statistics.median(timed_s(step, self.device, steps, warmup)), first


class GpuCheck:
    """Runs the sections of :class:`GpuCheckConfig` and collects their rows."""

    def __init__(self, config: GpuCheckConfig) -> None:
        self.config, self.size = config, SIZES[config.size]
        self.device = resolve_device(config.runtime.device)
        self.rows: list[Row] = []
        self.began = time.perf_counter()

    # -- bookkeeping --------------------------------------------------------------------------------------------

    def add(self, row: Row) -> None:
        self.rows.append(row)
        if self.config.runtime.progress:
            print(f"[{time.perf_counter() - self.began:6.1f} s] {row.section:<8} {row.name:<52} {row.value:>14}  "
                  f"{row.detail}", flush=True)

    @contextlib.contextmanager
    def row(self, section: str, name: str) -> Iterator[Row | None]:
        """A row to fill in; None (recorded as skipped) once the budget is spent. An exception in the body
        becomes the row's error, and the check goes on."""
        if time.perf_counter() - self.began > self.config.budget_s:
            self.add(Row(section, name, "-", f"not started: {self.config.budget_s:.0f} s budget spent", "skipped"))
            yield None
            return
        row = Row(section, name, "")
        try:
            yield row
        except Exception as err:  # the row records the failure; the rest of the check still runs
            row.value, row.status = "error", "failed"
            row.detail = f"{type(err).__name__}: {str(err).splitlines()[0][:300] if str(err) else ''}"
        finally:
            _free(self.device)
        self.add(row)

    # -- sections ------------------------------------------------------------------------------------------------

    def train_rows(self) -> None:
        for preset in self.size.presets:
            for precision in PRECISIONS:
                trainer = self._speed_row("train", preset, precision, compile_model=False)
                if trainer is not None:
                    self._largest_batch(preset, precision, trainer)
                del trainer

    def compile_rows(self) -> None:
        """The eager training rows at the table's batch again, compiled (last by default: compiling takes the
        longest, and the budget then skips these rather than the end-to-end sections)."""
        if self.size.compile:
            for preset in self.size.presets:
                for precision in PRECISIONS:
                    self._speed_row("compile", preset, precision, compile_model=True)

    def _speed_row(self, section: str, preset: str, precision: Precision, compile_model: bool) -> _Trainer | None:
        """Samples/s at the table's batch; returns the trainer (None if the row did not run)."""
        trainer = None
        mode = "torch.compile" if compile_model else "eager"
        with self.row(section, f"{preset} {precision} {mode}, batch {self.size.batch}") as row:
            if row is not None:
                trainer = _Trainer(preset, self.device, precision, compile_model)
                speed, first = trainer.steps_per_s(self.size.batch, self.size.steps, warmup=2)
                row.value = f"{speed:,.0f} samples/s"
                row.detail = self._memory(f"first step (compilation) {first:.1f} s" if compile_model
                                          else f"{trainer.params / 1e6:.1f}M parameters")
        return trainer

    def _largest_batch(self, preset: str, precision: Precision, trainer: _Trainer) -> None:
        """Double the batch from twice the table's until a step runs out of memory (or ``max_batch``)."""
        with self.row("train", f"{preset} {precision} eager, largest batch") as row:
            if row is None:
                return
            fits, batch = None, 2 * self.size.batch
            while batch <= self.size.max_batch:
                try:
                    trainer.steps_per_s(batch, 1, warmup=0)
                except Exception as err:
                    if not _is_out_of_memory(err):
                        raise
                    trainer.optimizer.zero_grad(set_to_none=True)
                    break
                finally:
                    _free(self.device)
                fits, batch = batch, 2 * batch
            if fits is None:
                row.value, row.detail = "-", f"batch {2 * self.size.batch} does not fit"
                return
            speed, _ = trainer.steps_per_s(fits, max(1, self.size.steps // 3), warmup=1)
            cap = " (the check's cap)" if fits * 2 > self.size.max_batch else ""
            row.value = f"{speed:,.0f} samples/s"
            row.detail = self._memory(f"batch {fits}{cap}")

    def latency_rows(self) -> None:
        samplers = [("DUST N_A=4, N_o=4", {}), ("DUST N_A=4, N_o=16", {"vision_step_ratio": 4}),
                    ("DUST N_A=4, N_o=32", {"vision_step_ratio": 8}), ("action-only N_A=4", {"variant": "action_only"})]
        for name, settings in samplers:
            for batch_size in self.size.latency_batches:
                with self.row("latency", f"{name}, batch {batch_size}") as row:
                    if row is None:
                        continue
                    torch.manual_seed(0)
                    config = DustConfig(**settings)
                    model = DustModel(config).to(self.device).eval()
                    obs = _device_batch(config, batch_size, self.device).select("state", "cond_tokens")
                    schedule, generator = schedule_for(config), torch.Generator().manual_seed(0)
                    with torch.inference_mode():
                        times = timed_s(functools.partial(model.predict_action, obs, schedule, generator),
                                        self.device, self.size.repeats, warmup=3)
                    row.value = f"{1e3 * statistics.median(times):.2f} ms/chunk"
                    row.detail = f"best {1e3 * min(times):.2f} ms, {len(schedule)} denoising passes"

    def ddp_rows(self) -> None:
        out = self.config.out
        data, run = out / "dataset", out / "run"
        for folder in (data, run):
            shutil.rmtree(folder, ignore_errors=True)
        with self.row("ddp", f"dust-rl collect: {self.size.episodes} {TASK} episodes") as row:
            if row is None:
                return
            seconds = self._cli(["collect", "--task", TASK, "--episodes", str(self.size.episodes), "--out", str(data),
                                 "--runtime.no-progress"])
            row.value, row.detail = f"{seconds:.1f} s", "scripted expert, 128 px front + wrist cameras"
        if not data.is_dir():
            return
        half = self.size.train_steps // 2
        train_args = ["--recipe", "defaults", "--dataset", str(data), "--optim.steps", str(self.size.train_steps),
                      "--logging.checkpoint-every", str(half), "--optim.batch-size", str(self.size.train_batch),
                      "--runtime.device", self.config.runtime.device, "--logging.loggers", "csv",
                      "--runtime.no-progress"]
        if self.config.text_encoder is not None:
            train_args += ["--model.text-encoder", str(self.config.text_encoder)]
        backend = "NCCL" if self.device.type == "cuda" else "gloo"
        with self.row("ddp", f"torchrun --nproc-per-node 1 ({backend}), {self.size.train_steps} steps") as row:
            if row is None:
                return
            seconds = self._torchrun([*train_args, "--out", str(run)])
            row.value, row.detail = f"{seconds:.1f} s", "collect's dataset; feature caching included"
        with self.row("ddp", f"resume from step {half} (torchrun)") as row:
            if row is None:
                return
            uninterrupted = run / "policy_uninterrupted.pt"
            _cut_back(run, half, uninterrupted)
            seconds = self._torchrun([*train_args, "--out", str(run), "--resume"])
            gap = _largest_weight_gap(uninterrupted, run / "policy.pt")
            row.value = f"{seconds:.1f} s"
            row.detail = f"largest weight difference from the uninterrupted run: {gap:.3g}"
        if self.device.type != "cuda":
            return
        with self.row("ddp", f"the GPU run resumed from step {half} on a CPU without CUDA") as row:
            if row is None:
                return
            _cut_back(run, half, run / "policy_resumed.pt")
            on_cpu = [*train_args, "--runtime.device", "cpu"]  # the later flag wins
            seconds = _run_python(["-m", "dust_rl.train", *on_cpu, "--out", str(run), "--resume"],
                                  self.config.out / "logs" / "resume_on_cpu.log", {"CUDA_VISIBLE_DEVICES": ""})
            gap = _largest_weight_gap(uninterrupted, run / "policy.pt")
            row.value = f"{seconds:.1f} s"
            row.detail = f"largest weight difference from the uninterrupted GPU run: {gap:.3g} (CPU arithmetic)"

    def eval_rows(self) -> None:
        policy = self.config.out / "run" / "policy.pt"
        with self.row("eval", f"dust-rl eval: {self.size.episodes} {TASK} episodes, rendering") as row:
            if row is None:
                return
            if not policy.is_file():
                raise FileNotFoundError(f"{policy}: the ddp section trains the policy this row evaluates")
            folder = self.config.out / "eval"
            args = ["eval", "--policy", str(policy), "--out", str(folder), "--episodes", str(self.size.episodes),
                    "--workers", "1", "--videos", "0", "--runtime.device", self.config.runtime.device,
                    "--runtime.no-progress"]
            if self.size.eval_max_steps:
                args += ["--max-steps", str(self.size.eval_max_steps)]
            seconds = self._cli(args)
            report = json.loads((folder / "report.json").read_text())
            overall = report["overall"]
            row.value = f"{seconds:.1f} s"
            row.detail = (f"MUJOCO_GL={os.environ.get('MUJOCO_GL', 'default')}; success {overall['success_rate']:.0%}"
                          f" (untrained policy); {_speed(report)}")

    # -- helpers -------------------------------------------------------------------------------------------------

    def _memory(self, detail: str) -> str:
        peak = _peak_gib(self.device)
        return detail if peak is None else f"{detail}; peak {peak:.1f} GiB"

    def _cli(self, args: list[str]) -> float:
        return _run_python(["-m", "dust_rl.cli", *args], self.config.out / "logs" / f"{args[0]}.log")

    def _torchrun(self, args: list[str]) -> float:
        log = self.config.out / "logs" / f"torchrun{'_resume' if '--resume' in args else ''}.log"
        return _run_python(["-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "1",
                            "-m", "dust_rl.train", *args], log)

    def run(self) -> list[Row]:
        sections = {"train": self.train_rows, "latency": self.latency_rows, "ddp": self.ddp_rows,
                    "eval": self.eval_rows, "compile": self.compile_rows}
        for name in self.config.sections:
            sections[name]()
        return self.rows


def _cut_back(run: pathlib.Path, step: int, keep_policy_as: pathlib.Path) -> None:
    """Leave ``run`` as a run killed after its step-``step`` checkpoint, its finished policy moved aside."""
    (run / "policy.pt").rename(keep_policy_as)
    for checkpoint in (run / "checkpoints").iterdir():
        if int(checkpoint.name.rsplit("-", 1)[1]) > step:
            shutil.rmtree(checkpoint)


def _run_python(args: list[str], log: pathlib.Path, env: dict[str, str] | None = None) -> float:
    """Seconds a ``python ARGS`` child took (``env`` added to this process's environment); its output goes to
    ``log``, whose error lines become the row's error if it fails."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True, env={**os.environ, **(env or {})})
    log.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(log, done.stdout + done.stderr)
    if done.returncode:
        lines = (done.stdout + done.stderr).strip().splitlines()
        errors = [line for line in lines if "dust-rl: error" in line or line.startswith(("[rank", "Traceback"))
                  or (line[:1].isalpha() and "Error" in line.split(":")[0] and "ChildFailedError" not in line)]
        raise RuntimeError(f"exit {done.returncode}: {' | '.join((errors or lines)[-2:])} (whole output: {log})")
    return time.perf_counter() - start


def _largest_weight_gap(first: pathlib.Path, second: pathlib.Path) -> float:
    """Largest absolute difference between two policy files' tensors (0.0: identical, non-finite entries
    such as unbounded action limits compared as equal when both files hold the same)."""
    a, b = (torch.load(path, map_location="cpu", weights_only=True)["state_dict"] for path in (first, second))
    gap = 0.0
    for key, x in a.items():
        x, y = x.double(), b[key].double()
        differ = ~((x == y) | (x.isnan() & y.isnan()))
        if differ.any():
            gap = max(gap, (x - y).abs()[differ].max().item())
    return gap


def _speed(report: dict) -> str:
    episodes_per_s = report["overall"]["episodes"] / report["episodes_time_s"]
    return f"{episodes_per_s:.2f} episodes/s, {report['env_steps_per_s']:.0f} env steps/s"


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)"


def table(rows: list[Row], device: torch.device) -> str:
    """The rows as a markdown table, headed by the device, torch version and date."""
    lines = [f"GPU check on {device_name(device)}, torch {torch.__version__}, "
             f"{datetime.date.today().isoformat()}", "",
             "| section | measurement | result | detail |", "|---|---|---|---|"]
    lines += [f"| {r.section} | {r.name} | {r.value} | {r.detail} |" for r in rows]
    return "\n".join(lines) + "\n"


def gpu_check_command(config: GpuCheckConfig, command: str | None = None) -> None:
    """``dust-rl bench gpu``: run the check, print and store the table.

    Raises:
        CheckFailedError: a row failed (after the table is written).
    """
    check = GpuCheck(config)
    config.out.mkdir(parents=True, exist_ok=True)
    with torch_threads(config.runtime.thread_count):
        rows = check.run()
    text = table(rows, check.device)
    write_text_atomic(config.out / "table.md", text)
    write_json_atomic(config.out / "results.json", {
        "device": device_name(check.device), "torch": torch.__version__, "command": command,
        "config": config_json(config), "rows": [asdict(r) for r in rows]})
    print(text)
    failed = [f"{r.section}: {r.name}" for r in rows if r.status == "failed"]
    if failed:
        raise CheckFailedError(f"{len(failed)} row(s) failed ({'; '.join(failed)}); their errors: "
                               f"{config.out / 'table.md'}")
