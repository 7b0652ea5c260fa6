"""Why does DUST's own future not help its actions when the true one does? Feed the actions futures between the two.

Why: the oracle-future test (``dust-rl diagnose world-model``) finds the actions' error against the demonstration
a third lower with the true t+H future in the vision stream than with noise, and no lower with the world model's
own sample, although that sample is closer to the real frame than the present frame is. Two readings fit: the
sample misses what the actions read (its content), or the action stream, trained only on noised true futures,
does not read any future that is not one (its inputs). Here the vision stream holds, re-noised to each step's
tau_o as in the test, ``own + alpha * (true - own)`` for alpha from 0 (the own sample, given) to 1 (the true
future), and the true future plus Gaussian noise of the own sample's mean squared error ("true + noise"): if
the actions' error falls with alpha in step with the future's error, and the noised true future keeps most of
the gain, a world model that errs less would help in proportion; if the gain only comes near alpha = 1, the
actions read details no imperfect future carries.

    .venv/bin/python experiments/future_interpolation.py \
        --policy runs/bench/pb200_plain/train/dust_seed0_demos200/policy.pt \
        --dataset runs/bench/pb200_plain/data/heldout_20
"""

from __future__ import annotations

import argparse
import pathlib

import torch

from dust_rl.agents import load_policy
from dust_rl.diagnose.world_model import (
    WorldModelDiagnosis,
    draw_windows,
    mean_interval,
    own_samples,
    per_window_error,
    renoised_source,
)
from dust_rl.runtime.settings import RuntimeSettings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--dataset", type=pathlib.Path, required=True, help="episodes the policy was not trained on")
    parser.add_argument("--windows", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75, 0.9, 1.0])
    args = parser.parse_args()
    torch.set_num_threads(1)

    policy = load_policy(args.policy).eval()
    config = WorldModelDiagnosis(policy=args.policy, dataset=args.dataset, windows=args.windows, seed=args.seed,
                                 runtime=RuntimeSettings(progress=False))
    windows = draw_windows(config, policy)
    batch, episode = windows.batch, windows.episode
    action, true = batch.get("action_chunk"), batch.get("future_tokens")
    pad = batch.get("action_is_pad", None)
    valid = None if pad is None else ~pad
    clamped = batch.get("future_is_clamped", torch.zeros(len(true), dtype=torch.bool))
    inside = ~clamped  # windows whose t+H frame is inside the episode
    noise = torch.randn(true.shape, generator=torch.Generator().manual_seed(args.seed + 1))
    _, own = own_samples(policy, batch, args.seed, config.batch_size)

    own_error = per_window_error(own, true)
    jitter = torch.randn(true.shape, generator=torch.Generator().manual_seed(args.seed + 2))
    noised_true = true + jitter * own_error[inside].mean().sqrt()
    futures = {f"alpha {alpha:g}": own + alpha * (true - own) for alpha in args.alphas}
    futures["true + noise"] = noised_true
    futures["noise"] = None
    print(f"{len(true)} windows ({int(inside.sum())} with t+H inside the episode), {int(episode.unique().numel())} "
          "episodes; errors: mean over episodes [95% CI]")
    print("| vision stream holds | future's error (t+H inside) | action error |")
    print("|---|---|---|")
    for name, future in futures.items():
        chunks, _ = own_samples(policy, batch, args.seed, config.batch_size, renoised_source(future, noise))
        acted = mean_interval(per_window_error(chunks, action, valid), episode)
        if future is None:
            future_cell = "-"
        else:
            seen = mean_interval(per_window_error(future, true)[inside], episode[inside])
            future_cell = f"{seen['mean']:.4f} [{seen['ci95_low']:.4f}, {seen['ci95_high']:.4f}]"
        print(f"| {name} | {future_cell} | {acted['mean']:.4f} [{acted['ci95_low']:.4f}, {acted['ci95_high']:.4f}] |")


if __name__ == "__main__":
    main()
