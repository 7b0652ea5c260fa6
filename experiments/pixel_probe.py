"""Can the pixel-keypoint network find the named cube? A regression on frames whose objects do not follow the arm.

Renders ``--frames`` aux frames of pick_place (random resets and random arm motions,
:mod:`dust_rl.train.readout.aux_frames`), fits :class:`~dust_rl.agents.heads.pixel_keypoints.PixelKeypoints` on
front and wrist plus an MLP from the keypoint coordinates and the named colour to the target cube's and the plate's
xy on 80% of them, and prints the mean error on the rest every 500 steps, beside predicting the mean.

    .venv/bin/python experiments/pixel_probe.py [--frames 3000] [--steps 4000] [--lr 1e-3]
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F
from torch import nn

from dust_rl.agents.heads.pixel_keypoints import PixelKeypoints
from dust_rl.envs.tasks.base import COLORS
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY
from dust_rl.train.readout.aux_frames import render_aux_frames

CAMERAS = ["front", "wrist"]
KEYPOINTS, BATCH, EVERY = 16, 64, 500
TARGET_XY, PLATE_XY = slice(0, 2), slice(6, 8)  # pick_place's object state: target, distractor, plate xyz


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--lr", type=float, default=1e-3)
    args = parser.parse_args()
    torch.manual_seed(0)
    rows, instructions = render_aux_frames("DustFranka-v0", {}, ["pick_place"], CAMERAS, args.frames, 9)
    state = rows.get(ENV_STATE_KEY)
    target = torch.cat([state[:, TARGET_XY], state[:, PLATE_XY]], dim=1)
    colour = F.one_hot(torch.tensor([next(i for i, c in enumerate(COLORS) if f" {c} " in text)
                                     for text in instructions]), len(COLORS)).float()
    frames = [rows.get((*IMAGE_KEY, cam)) for cam in CAMERAS]
    fit = int(0.8 * args.frames)
    mean, std = target[:fit].mean(0), target[:fit].std(0)
    networks = nn.ModuleList(PixelKeypoints(KEYPOINTS) for _ in CAMERAS)
    head = nn.Sequential(nn.Linear(2 * KEYPOINTS * len(CAMERAS) + len(COLORS), 256), nn.GELU(),
                         nn.Linear(256, 256), nn.GELU(), nn.Linear(256, 4))
    optimizer = torch.optim.AdamW([*networks.parameters(), *head.parameters()], args.lr)

    def predict(index: torch.Tensor, augment: bool) -> torch.Tensor:
        points = [net(images[index], augment)[0].flatten(1) for net, images in zip(networks, frames, strict=True)]
        return head(torch.cat([*points, colour[index]], dim=1))

    def cm(a: torch.Tensor, b: torch.Tensor) -> float:
        return 100 * (a - b).norm(dim=1).mean().item()

    held_out = torch.arange(fit, args.frames)
    print(f"predicting the mean: target {cm(mean[:2], target[held_out, :2]):.1f} cm, "
          f"plate {cm(mean[2:], target[held_out, 2:]):.1f} cm")
    for step in range(1, args.steps + 1):
        index = torch.randint(0, fit, (BATCH,))
        loss = F.mse_loss(predict(index, True), (target[index] - mean) / std)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step % EVERY == 0:
            with torch.no_grad():
                guess = predict(held_out, False) * std + mean
            print(f"step {step}: target {cm(guess[:, :2], target[held_out, :2]):.1f} cm, "
                  f"plate {cm(guess[:, 2:], target[held_out, 2:]):.1f} cm", flush=True)


if __name__ == "__main__":
    main()
