"""Where a policy step's time goes, by torch op: ``torch.profiler`` over a trained run's policy steps, and the
cross-attention key/value ``bmm`` alone (the matmul that sets the AVX-512 vs AVX2 difference; run it again with
``MKL_ENABLE_INSTRUCTIONS=AVX2`` to see it).

    .venv/bin/python experiments/profile_train_step.py runs/bench/ts_avx512   # a `dust-rl bench train-speed` --out
"""

from __future__ import annotations

import argparse
import pathlib
import time

import torch
from torch.profiler import ProfilerActivity, profile

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache
from dust_rl.train.optim import adamw


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bench", type=pathlib.Path, help="a `dust-rl bench train-speed --out` folder")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = load_policy(args.bench / "train" / "policy.pt")
    dataset = DemoDataset(args.bench / "data")
    features = FeatureCache(dataset, policy, progress=False, store=True)
    windows = DemoWindows(dataset, horizon=policy.config.horizon, future_offset=policy.config.future_steps,
                          batch_size=64, images=False)
    policy.train()
    policy.readout.frame_modules().requires_grad_(False)
    optimizer = adamw([p for p in policy.trainable_modules().parameters() if p.requires_grad], 1e-4)

    def step() -> None:
        losses = policy.compute_loss(features.batch(windows.sample()))
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()

    for _ in range(3):
        step()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for _ in range(args.steps):
            step()
    print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=15,
                                                             max_name_column_width=30, max_shapes_column_width=80))
    keys, weights = torch.randn(2, 9216, 256), torch.randn(2, 256, 128)  # [S, B * 144 tokens, d] at batch 64
    for _ in range(3):
        torch.bmm(keys, weights)
    began = time.perf_counter()
    for _ in range(50):
        torch.bmm(keys, weights)
    print(f"bmm [2, 9216, 256] x [2, 256, 128]: {(time.perf_counter() - began) / 50 * 1000:.1f} ms "
          f"(kernels {torch.backends.cpu.get_cpu_capability()})")


if __name__ == "__main__":
    main()
