"""Can DUST's predicted futures tell which of K sampled chunks the simulator would rank first?

Why: best-of-K selection by the world model (``wm_select``) needs a scorer of predicted futures that ranks the K
joint samples of one situation as their outcomes would. The earlier scorer was fitted on outcome labels of whole
episodes, so it never saw two samples of one situation with different outcomes. Here the search expert
(:mod:`dust_rl.search_expert`) labels every candidate of every plan by where the simulator says it lands, so a
scorer can be fitted on exactly that question: a ridge regression of the within-plan centred score on the
within-plan centred predicted future, fitted on four fifths of the episodes and judged on the rest by the
within-plan Spearman correlation and by the score its pick gains over the mean candidate (the oracle's pick: the
most any scorer could gain).

    .venv/bin/python scripts/future_ranking.py --policy runs/train/T/policy.pt [--candidates 8] [--lookahead 1] \
        [--seed 20000] [--episodes 60]
"""

from __future__ import annotations

import argparse
import pathlib

import torch
from lookahead_headroom import describe, run

from dust_rl.search_settings import SearchSettings
from dust_rl.wm_select import VALIDATION_EVERY  # every 5th episode judges the fit, as wm_select's scorer

RIDGE = (1e-1, 1.0, 10.0, 100.0, 1000.0)


def selection_gain(predicted: torch.Tensor, scores: torch.Tensor) -> float:
    """Mean score of each plan's pick by ``predicted`` [M, K], over the mean of its candidates' scores [M, K]."""
    picked = scores.gather(1, predicted.argmax(1, keepdim=True))[:, 0]
    return (picked - scores.mean(1)).mean().item()


def spearman_within(predicted: torch.Tensor, scores: torch.Tensor) -> float:
    """Mean over plans of the rank correlation between ``predicted`` and ``scores`` across its K candidates."""
    ranks = [x.argsort(1).argsort(1).float() for x in (predicted, scores)]
    a, b = (r - r.mean(1, keepdim=True) for r in ranks)
    return ((a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-9)).mean().item()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--candidates", type=int, default=8)
    parser.add_argument("--lookahead", type=int, default=1)
    parser.add_argument("--seed", type=int, default=20_000)
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds, settings = range(args.seed, args.seed + args.episodes), SearchSettings(args.candidates, args.lookahead)
    result = run(args.policy, settings, seeds, record=True)
    print(describe(settings, seeds, result))
    if result.choices[0].futures is None:
        raise SystemExit(f"{args.policy} predicts no future: nothing to rank")
    futures = torch.stack([c.futures for c in result.choices]).flatten(2).double()  # [M, K, N_o * Dv]
    scores = torch.stack([c.scores for c in result.choices]).double()  # [M, K]
    validation = torch.tensor(result.episode_of_choice) % VALIDATION_EVERY == VALIDATION_EVERY - 1
    centred = futures - futures.mean(1, keepdim=True)
    spread = futures.sub(futures.mean((0, 1))).pow(2).sum(-1).mean()
    print(f"{len(scores)} plans ({int(validation.sum())} judged); the candidates' share of the predicted futures' "
          f"variance: {centred.pow(2).sum(-1).mean() / spread:.3f}; scores differ by more than 0.01 in "
          f"{(scores.max(1).values - scores.min(1).values > 0.01).double().mean():.0%} of the plans")
    oracle = selection_gain(scores[validation], scores[validation])
    print(f"gain of the pick over the mean candidate (judged plans): oracle {oracle:.4f}")
    fit_x = centred[~validation].reshape(-1, centred.shape[-1])
    fit_y = (scores - scores.mean(1, keepdim=True))[~validation].reshape(-1)
    for ridge in RIDGE:
        weights = torch.linalg.solve(fit_x.T @ fit_x + ridge * torch.eye(fit_x.shape[1], dtype=fit_x.dtype),
                                     fit_x.T @ fit_y)
        predicted = centred @ weights
        print(f"ridge {ridge:g}: gain fitted {selection_gain(predicted[~validation], scores[~validation]):.4f}, "
              f"judged {selection_gain(predicted[validation], scores[validation]):.4f}; Spearman judged "
              f"{spearman_within(predicted[validation], scores[validation]):.3f}")


if __name__ == "__main__":
    main()
