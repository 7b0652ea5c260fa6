"""Can a policy's frozen inputs give the expert's first move? A small head fitted on them, as a bound.

For every demonstration of ``--dataset`` the frozen tokens of all cameras at step 0 (the policy's
own encoder and condition grid) and the pooled instruction embedding (its text encoder) are fitted
to the expert's first 8-step displacement (cm) by an attention-pooling head
(:mod:`dust_rl.agents.heads.attention_pooling`); the error (the best of its periodic checks) is on step 0 of
``--val-dataset``'s demonstrations, beside the error of predicting no move.
``experiments/first_move_error.py`` gives the same number for
the policy itself: where the head is far better, the information is in the inputs and the policy
does not learn to use it.

    .venv/bin/python experiments/first_move_probe.py --policy runs/train/T/policy.pt \\
        --dataset runs/data/pick_place_2000 --val-dataset runs/data/pick_place_val
"""

from __future__ import annotations

import argparse
import time

import torch
from torch import Tensor, nn
from tqdm import trange

from dust_rl.agents import load_policy
from dust_rl.agents.encoders.text_encoder import pooled_text
from dust_rl.agents.heads.attention_pooling import WIDTH, AttentionProbe, standardise
from dust_rl.agents.policy import DustPolicy
from dust_rl.data import DemoDataset
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.keys import EXPERT_ACTION_KEY, IMAGE_KEY

SPAN, CM_PER_UNIT = 8, 100 * MAX_TRANSLATION
STEPS, BATCH, EVERY = 3000, 128, 500


def first_moves(policy: DustPolicy, path: str) -> tuple[Tensor, Tensor, Tensor]:
    """Step-0 tokens [E, C*N, D], pooled instruction [E, Dt] and the expert's 8-step move in cm [E, 3]."""
    dataset = DemoDataset(path)
    rows = dataset.episode_starts
    moves = torch.stack([dataset.data[EXPERT_ACTION_KEY][row:row + SPAN, :3].sum(0) for row in rows.tolist()])
    images = dataset.data.select(IMAGE_KEY)  # read only the frames of the rows below
    with torch.no_grad():
        tokens = torch.cat([policy.image_features(images[rows[i:i + 64]]) for i in range(0, len(rows), 64)])
        texts = [dataset.instructions[episode["instruction_index"]] for episode in dataset.meta["episodes"]]
        text = pooled_text(*policy.backbone.text_tokens(texts))
    return tokens.flatten(1, 2).float(), text.float(), CM_PER_UNIT * moves


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="whose frozen encoders give the inputs")
    parser.add_argument("--dataset", required=True, help="demonstrations to fit on")
    parser.add_argument("--val-dataset", required=True, help="demonstrations of other seeds to measure on")
    parser.add_argument("--seed", type=int, default=0, help="head weights and batches")
    parser.add_argument("--late-text", action="store_true",
                        help="the instruction joins after the pooling, not every token (as the trunk sees it)")
    args = parser.parse_args()
    began = time.perf_counter()
    torch.manual_seed(args.seed)
    policy = load_policy(args.policy).eval()
    x, text, move = first_moves(policy, args.dataset)
    x_val, text_val, move_val = first_moves(policy, args.val_dataset)
    x, x_val = standardise(x, x_val)
    probe = AttentionProbe(x.shape[1], x.shape[2], lambda: nn.Linear(text.shape[1], WIDTH), outputs=3,
                           early=not args.late_text)
    optimizer = torch.optim.AdamW(probe.parameters(), lr=1e-3, weight_decay=1e-2)
    best = float("inf")
    for step in trange(STEPS + 1, desc="probe"):
        rows = torch.randint(0, len(x), (BATCH,))
        loss = (probe(x[rows], text[rows]) - move[rows]).square().sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step % EVERY == 0:
            with torch.no_grad():
                best = min(best, (probe(x_val, text_val) - move_val).norm(dim=-1).mean().item())
    print(f"first {SPAN}-step move of {len(move_val)} validation demos, head fitted on {len(move)} first frames: "
          f"{best:.1f} cm off (no move: {move_val.norm(dim=-1).mean():.1f} cm); {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
