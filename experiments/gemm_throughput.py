"""How fast this CPU runs the trunk's largest fp32 matrix products, through MKL (torch's default) and oneDNN.

Tells a slow machine from a slow code path: on a 2-core AMD EPYC (Zen 3, AVX2) MKL reports its generic "Intel(R)
Architecture processors" path, yet oneDNN's JIT kernels, which dispatch on the ISA alone, are no faster there
(docs/results/2026-12-02-amd-avx2-speed.md).

    .venv/bin/python experiments/gemm_throughput.py --threads 1   # MKL_VERBOSE=1 prints the path MKL chose
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch


def milliseconds(call: Callable[[], object], repeats: int = 20) -> float:
    for _ in range(3):
        call()
    began = time.perf_counter()
    for _ in range(repeats):
        call()
    return (time.perf_counter() - began) / repeats * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    # [S, B * 144 condition tokens, d] x [S, d, 2d] at batch 64, and all cross blocks' K/V as one product
    keys, weights = torch.randn(2, 9216, 256), torch.randn(2, 256, 128)
    rows, wide = torch.randn(9216, 128), torch.randn(1536, 128)
    wide_mkldnn, rows_mkldnn, bias = wide.to_mkldnn(), rows.to_mkldnn(), torch.zeros(1536).to_mkldnn()
    cases = {"bmm [2, 9216, 256] x [2, 256, 128] (MKL)": (lambda: torch.bmm(keys, weights), 2 * 9216 * 256 * 128),
             "linear 9216 x 128 -> 1536 (MKL)": (lambda: torch.nn.functional.linear(rows, wide), 9216 * 128 * 1536),
             "linear 9216 x 128 -> 1536 (oneDNN)": (lambda: torch._C._nn.mkldnn_linear(rows_mkldnn, wide_mkldnn, bias),
                                                    9216 * 128 * 1536)}
    print(f"{torch.get_num_threads()} threads, kernels {torch.backends.cpu.get_cpu_capability()}")
    for name, (call, multiply_adds) in cases.items():
        ms = milliseconds(call)
        print(f"{name}: {ms:.1f} ms, {2 * multiply_adds / ms / 1e6:.0f} GFLOP/s")


if __name__ == "__main__":
    main()
