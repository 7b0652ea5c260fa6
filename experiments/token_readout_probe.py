"""How many centimetres off is the token read-out (``--model.readout tokens``), object by object?

Fits only the read-out, as ``dust-rl train --readout.aux-frames N --readout.warmup-steps S --readout.no-demos`` warms it
up (the same frames: seeds from ``dust_rl.train.readout.aux_frames.FIRST_SEED``, the same held-out ones), and
prints each
object's xy error on the held-out frames in cm, and the normalised squared error of every state column,
so a read-out that finds the named object but not the others (or the reverse) shows. The policy's image
tokens are standardised with the held-out frames' statistics here (training uses the demonstrations').

    .venv/bin/python experiments/token_readout_probe.py --dataset runs/data/press_button_200 --columns 4
"""

from __future__ import annotations

import argparse
import time

import torch
from readout_error import readout_error_table  # experiments/readout_error.py, beside this script

from dust_rl.agents import make_policy
from dust_rl.data import DemoDataset
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.train.readout.aux_frames import (
    FIRST_SEED,
    HELDOUT_FIRST_SEED,
    HELDOUT_FRAMES,
    AuxFrameBatches,
    render_aux_frames,
)
from dust_rl.train.readout.warmup import warm_up_readout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="the training demonstrations (env, cameras, state stats)")
    parser.add_argument("--frames", type=int, default=4000, help="aux frames to fit")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--heads", type=int, default=1, help="attention poolings of the read-out")
    parser.add_argument("--columns", type=int, default=3, help="object-state columns per object (press_button: 4)")
    parser.add_argument("--image-encoder", default="efficientnet-lite0-s8")
    parser.add_argument("--cond-grid", type=int, default=8)
    parser.add_argument("--grid", type=int, default=None, help="the read-out's token grid (16: the recipes')")
    parser.add_argument("--proprio", action="store_true", help="the read-out also reads the robot state")
    parser.add_argument("--text-attention", action="store_true", help="a learnt attention over the instruction")
    parser.add_argument("--close-up-fraction", type=float, default=0.0, help="share of close-up aux frames")
    parser.add_argument("--pooled-stats", action="store_true",
                        help="normalise the object state by the whole dataset's statistics, as before per-task ones "
                             "(dust_rl.data.env_state_norm), for comparison")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 beside a training)")
    parser.add_argument("--val-dataset", help="demonstrations on other seeds: also print the read-out's error on "
                                              "their rows by step of the episode (the table of "
                                              "experiments/readout_error.py)")
    args = parser.parse_args()
    began = time.perf_counter()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    dataset = DemoDataset(args.dataset)
    width = env_state_width(dataset)
    policy = make_policy(image_encoder=args.image_encoder, cond_grid=(args.cond_grid, args.cond_grid),
                         variant="action_only", readout="tokens", readout_heads=args.heads,
                         readout_grid=(args.grid, args.grid) if args.grid else None, readout_proprio=args.proprio,
                         readout_text="attention" if args.text_attention else "mean",
                         aux_state_dim=width, lambda_aux=1.0, **dataset_policy_kwargs(dataset))
    norm = EnvStateNorm.of_dataset(dataset, per_task=not args.pooled_stats)

    def frames(count: int, first_seed: int) -> AuxFrameBatches:
        rows, instructions = render_aux_frames(dataset.meta["env_id"], dataset.meta["env_kwargs"], dataset.tasks,
                                               policy.cameras, count, width, first_seed=first_seed,
                                               close_up_fraction=args.close_up_fraction)
        return AuxFrameBatches(rows, instructions, policy, norm)

    heldout = frames(HELDOUT_FRAMES, HELDOUT_FIRST_SEED)
    policy.normalizer.set_vision_stats(heldout.frames)
    fit = frames(args.frames, FIRST_SEED)
    policy.train()
    warm_up_readout(policy, None, fit, args.steps, 1e-3, lambda scalars, step: None, heldout=heldout)
    policy.eval()
    rows = heldout.rows(torch.arange(len(heldout)))
    with torch.no_grad():
        estimate = policy.estimate_env_state(rows)
    truth, task = rows.get("env_state"), heldout.task_index

    def xy(normalised: torch.Tensor) -> torch.Tensor:  # per object, in metres
        return norm.denormalize(normalised, task).unflatten(-1, (-1, args.columns))[..., :2]

    cm = 100 * (xy(estimate) - xy(truth)).norm(dim=-1).mean(0)
    spread = 100 * (xy(truth) - xy(truth).mean(0)).norm(dim=-1).mean(0)
    print(f"{args.frames} frames, {args.steps} steps, {args.heads} head(s), {time.perf_counter() - began:.0f} s; "
          f"held-out xy error per object (named first), cm: {[round(v, 1) for v in cm.tolist()]}; "
          f"predicting the mean: {[round(v, 1) for v in spread.tolist()]}")
    print("normalised squared error per column:", [round(v, 3) for v in (estimate - truth).square().mean(0).tolist()])
    if args.val_dataset:
        print(readout_error_table(policy, DemoDataset(args.val_dataset), norm, args.columns))


if __name__ == "__main__":
    main()
