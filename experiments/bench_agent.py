"""Benchmark the DUST model on CPU: chunk latency at batch 1 and training throughput.

Inputs are random stand-ins for cached backbone features (no backbone runs), so
the trunk rows measure the flow-matching trunk and sampler alone; the policy
rows add the frozen backbone (two 128 px cameras through each ``--image-encoders``
entry, the instruction's MiniLM tokens from the per-string cache) and
normalisation, as a torchrl policy sees them. Latency is the
wall time of one ``predict_action`` call (context encoding plus all denoising
steps); the table gives the median and the best of ``--repeats`` calls, the
best being the better estimate on a machine shared with other jobs, and the
median process CPU time per call, which with ``--threads 1`` estimates the
latency on an idle core even while other jobs share the machine. ``--compile``
(``torch.compile`` of the trunk, as ``--runtime.compile`` of train and eval) and
``--precision bf16`` (autocast) apply to the trunk rows and the training row;
the "first" column is the first call's wall time, with ``--compile`` the
compilation's cost.

Usage: python experiments/bench_agent.py [--threads 2] [--repeats 30] [--train-steps 8] [--compile]
       [--precision fp32|bf16] [--image-encoders conv-ae,efficientnet-lite0] [--policies PATH ...]

``--policies`` times trained policy files (their encoder, condition grid, variant and sampler as trained).
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import time
from collections.abc import Callable

import torch
from tensordict import TensorDict

from dust_rl.agents import (
    DustConfig,
    DustModel,
    DustPolicy,
    SamplerConfig,
    load_policy,
    make_policy,
    random_batch,
    schedule_for,
)
from dust_rl.agents.model.precision import Precision, autocast

N_COND_TOKENS = 40
CAMERAS = ("front", "wrist")
DEFAULT_POLICY_SAMPLERS = [("N_A=4, N_o=4", SamplerConfig("async", 4, 1)),
                           ("N_A=4, N_o=16", SamplerConfig("async", 4, 4)),
                           ("sync 4 steps", SamplerConfig("sync", 4, 1)),
                           ("action-only 4 steps", SamplerConfig("action_only", 4, 1))]


def first_call_s(fn: Callable[[], object]) -> float:
    """Wall time in seconds of one call (the first: it includes any compilation)."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def timed(fn: Callable[[], object], repeats: int, warmup: int = 3) -> tuple[list[float], list[float]]:
    """Wall and process CPU times in seconds of ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return wall, cpu


def chunk_latency_ms(config: DustConfig, repeats: int, compile_model: bool,
                     precision: Precision) -> tuple[float, float, float, float]:
    """Median and best wall time, median CPU time (ms) of one ``predict_action`` call at batch 1, and the
    first call's wall time (s)."""
    agent = DustModel(config).eval()
    if compile_model:
        agent.compile()
    generator = torch.Generator().manual_seed(0)
    obs = random_batch(config, 1, N_COND_TOKENS, generator).select("state", "cond_tokens")
    schedule = schedule_for(config)

    def call() -> None:
        with autocast(torch.device("cpu"), precision):
            agent.predict_action(obs, schedule, generator)

    first = first_call_s(call)
    wall, cpu = timed(call, repeats)
    return 1e3 * statistics.median(wall), 1e3 * min(wall), 1e3 * statistics.median(cpu), first


def policy_latency_ms(policy: DustPolicy, label: str, repeats: int,
                      samplers: list[tuple[str, SamplerConfig]]) -> list[tuple[str, float, float, float]]:
    """Median and best wall time and median CPU time (ms) of ``policy`` on raw observations at batch 1.

    Rows: the frozen backbone alone, then one ``plan`` call per sampler.
    """
    images = {cam: torch.randint(0, 256, (1, 3, 128, 128), dtype=torch.uint8) for cam in policy.cameras}
    state_dim = policy.normalizer.state_mean.shape[-1]
    obs = TensorDict({"observation": {"image": images, "state": torch.randn(1, state_dim)}}, batch_size=[1])
    obs["language_instruction"] = "press the red button"
    generator = torch.Generator().manual_seed(0)
    rows = []
    wall, cpu = timed(lambda: policy.observation_features(obs), repeats)
    grid = "x".join(map(str, policy.config.condition_grid))
    rows.append((f"{label} ({grid}/camera): {len(policy.cameras)} cameras 128 px", wall, cpu))
    for name, sampler in samplers:
        policy.set_sampler(sampler)
        wall, cpu = timed(lambda: policy.plan(obs, generator), repeats)
        rows.append((f"  policy {name} (ms/chunk)", wall, cpu))
    return [(name, 1e3 * statistics.median(w), 1e3 * min(w), 1e3 * statistics.median(c)) for name, w, c in rows]


def train_samples_per_s(config: DustConfig, batch_size: int, steps: int, compile_model: bool,
                        precision: Precision) -> tuple[float, float, float, float]:
    """Training throughput (forward, backward, fused AdamW step) on random cached features.

    Returns samples/s from the median and the best wall time, and from the median CPU time, and the first
    step's wall time (s).
    """
    agent = DustModel(config).train()
    if compile_model:
        agent.compile()
    optimizer = torch.optim.AdamW(agent.parameters(), lr=1e-4, fused=True)  # fused: ~5x faster step on CPU
    generator = torch.Generator().manual_seed(0)
    batch = random_batch(config, batch_size, N_COND_TOKENS, generator)

    def step() -> None:
        with autocast(torch.device("cpu"), precision):
            loss = agent.compute_loss(batch, generator)["loss"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    first = first_call_s(step)
    wall, cpu = timed(step, steps, warmup=2)
    return batch_size / statistics.median(wall), batch_size / min(wall), batch_size / statistics.median(cpu), first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--train-steps", type=int, default=8)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--compile", action="store_true", help="torch.compile the trunk (trunk and training rows)")
    parser.add_argument("--precision", choices=["fp32", "bf16"], default="fp32", help="autocast of the trunk rows")
    parser.add_argument("--image-encoders", default="conv-ae,efficientnet-lite0",
                        help="comma-separated encoders of the default-size policy rows ('' for none)")
    parser.add_argument("--policies", nargs="*", default=[], metavar="PATH",
                        help="trained policy files (dust-rl train) to time with the sampler they were trained for")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    base = DustConfig()
    params = sum(p.numel() for p in DustModel(base).parameters())
    print(
        f"DUST d_model={base.d_model} heads={base.n_heads} blocks={base.n_mmdit}+{base.n_dit} "
        f"params={params / 1e6:.2f}M H={base.horizon} N_o={base.n_vision_tokens} Nc={N_COND_TOKENS} "
        f"threads={args.threads} compile={args.compile} precision={args.precision}"
    )
    rows = [
        ("DUST N_A=4, N_o=4 (ms/chunk, batch 1)", DustConfig(), "<= 25"),
        ("DUST N_A=4, N_o=16 (ms/chunk, batch 1)", DustConfig(vision_step_ratio=4), "<= 60"),
        ("DUST N_A=4, N_o=32 (ms/chunk, batch 1)", DustConfig(vision_step_ratio=8), ""),
        ("action_only N_A=4 (ms/chunk, batch 1)", DustConfig(variant="action_only"), ""),
    ]
    print(f"| {'measurement':<44} | {'median':>8} | {'best':>8} | {'cpu':>8} | {'first (s)':>9} | {'target':>8} |")
    print(f"|{'-' * 46}|{'-' * 10}|{'-' * 10}|{'-' * 10}|{'-' * 11}|{'-' * 10}|")
    for name, config, target in rows:
        median, best, cpu, first = chunk_latency_ms(config, args.repeats, args.compile, args.precision)
        print(f"| {name:<44} | {median:8.2f} | {best:8.2f} | {cpu:8.2f} | {first:9.2f} | {target:>8} |", flush=True)
    policies = [(encoder, make_policy("dust", image_encoder=encoder, cameras=CAMERAS, action_dim=7,
                                      state_dim=17), DEFAULT_POLICY_SAMPLERS)
                for encoder in args.image_encoders.split(",") if encoder]
    for path in args.policies:
        policy = load_policy(path)
        sampler = policy.config.sampler_settings
        name = f"{policy.config.variant}, N_A={sampler.n_action_steps}, q={sampler.vision_step_ratio}"
        policies.append((pathlib.Path(path).parent.name, policy, [(name, sampler)]))
    for label, policy, samplers in policies:
        for name, median, best, cpu in policy_latency_ms(policy, label, args.repeats, samplers):
            target = "<= 25" if "N_A=4, N_o=4" in name else ""
            print(f"| {name:<44} | {median:8.2f} | {best:8.2f} | {cpu:8.2f} | {'':>9} | {target:>8} |", flush=True)
    median, best, cpu, first = train_samples_per_s(base, args.batch_size, args.train_steps, args.compile,
                                                   args.precision)
    name = f"DUST training (samples/s, batch {args.batch_size})"
    print(f"| {name:<44} | {median:8.1f} | {best:8.1f} | {cpu:8.1f} | {first:9.2f} | {'>= 300':>8} |")


if __name__ == "__main__":
    main()
