"""How precisely do an encoder's frozen tokens give the named cube's position, and from how many layouts?

Renders the front camera at reset for ``--train`` pick_place layouts (seeds from 100,000) and 200
validation layouts (seeds 5000..5199), encodes them with EfficientNet-Lite0 cut at ``--stride`` and pooled
to ``--grid``, and fits a small attention-pooling head (tokens plus the named colour -> the target
cube's xy). Prints the best validation error over training beside predicting the mean. Unlike
``dust-rl encoder check`` (linear probes of whole demonstration episodes) every frame is a fresh layout
with the arm at home, the view a policy must act on at the first step.

    .venv/bin/python experiments/frozen_feature_probe.py --stride 8 --grid 8 --train 2000
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import torch
from torch import Tensor, nn

import dust_rl  # noqa: F401  (registers the envs)
from dust_rl.agents.encoders.efficientnet_lite import EfficientNetLite
from dust_rl.agents.encoders.image_encoder import image_tokens
from dust_rl.agents.heads.attention_pooling import WIDTH, AttentionProbe, standardise
from dust_rl.envs.tasks.base import COLORS
from dust_rl.keys import ENV_STATE_KEY, INSTRUCTION_KEY, flat_name

TRAIN_SEED, VAL_SEEDS = 100_000, range(5000, 5200)
STEPS, BATCH, EVERY = 4000, 128, 500


def layouts(env: gym.Env, encoder: EfficientNetLite, seeds: range, grid: int) -> tuple[Tensor, Tensor, Tensor]:
    """Tokens [S, grid^2, D], named colour index [S] and target xy in cm [S, 2] of the reset frames."""
    frames, colours, targets = [], [], []
    names = list(COLORS)
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        frames.append(torch.as_tensor(obs[flat_name(("observation", "image", "front"))]).permute(2, 0, 1))
        colours.append(next(i for i, name in enumerate(names) if f" {name} " in obs[INSTRUCTION_KEY]))
        targets.append(100 * torch.as_tensor(obs[flat_name(ENV_STATE_KEY)][:2]))
    stacked = torch.stack(frames)
    with torch.no_grad():
        tokens = torch.cat([image_tokens(encoder, stacked[i:i + 64], (grid, grid)) for i in range(0, len(stacked), 64)])
    return tokens.float(), torch.tensor(colours), torch.stack(targets).float()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stride", type=int, default=16, choices=(8, 16, 32), help="Lite0 feature stride")
    parser.add_argument("--grid", type=int, default=None, help="token grid side (default: the map's own)")
    parser.add_argument("--train", type=int, default=2000, help="training layouts")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0, help="probe weights and batches")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    began = time.perf_counter()
    grid = args.grid or args.image_size // args.stride
    encoder = EfficientNetLite(feature_stride=args.stride, image_size=args.image_size).eval()
    env = gym.make("DustFranka-v0", task="pick_place", image_size=args.image_size, cameras=("front",))
    x, colour, target = layouts(env, encoder, range(TRAIN_SEED, TRAIN_SEED + args.train), grid)
    x_val, colour_val, target_val = layouts(env, encoder, VAL_SEEDS, grid)
    env.close()
    x, x_val = standardise(x, x_val)
    centre = target.mean(0)
    probe = AttentionProbe(x.shape[1], x.shape[2], lambda: nn.Embedding(len(COLORS), WIDTH), outputs=2)
    optimizer = torch.optim.AdamW(probe.parameters(), lr=1e-3, weight_decay=1e-2)
    best = float("inf")
    for step in range(STEPS + 1):
        rows = torch.randint(0, len(x), (BATCH,))
        loss = (probe(x[rows], colour[rows]) + centre - target[rows]).square().sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step % EVERY == 0:
            with torch.no_grad():
                best = min(best, (probe(x_val, colour_val) + centre - target_val).norm(dim=-1).mean().item())
    guess = (target_val - centre).norm(dim=-1).mean().item()
    print(f"Lite0 stride {args.stride}, {grid}x{grid} tokens x {x.shape[2]}, {args.image_size} px, "
          f"{args.train} training layouts: named cube's xy {best:.1f} cm off on {len(VAL_SEEDS)} validation "
          f"layouts (the mean: {guess:.1f} cm); {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
