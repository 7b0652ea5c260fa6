"""Can DUST's predicted futures, or the chunk and the situation, tell which of K sampled chunks the simulator
would rank first?

Why: best-of-K selection by the world model (``wm_select``) needs a scorer of predicted futures that ranks the K
joint samples of one situation as their outcomes would. The earlier scorer was fitted on outcome labels of whole
episodes, so it never saw two samples of one situation with different outcomes. Here the search expert
(:mod:`dust_rl.search_expert`) labels every candidate of every plan by where the simulator says it lands, so a
scorer can be fitted on exactly that question: a ridge regression of the within-plan centred score on the
within-plan centred predicted future, fitted on four fifths of the episodes and judged on the rest by the
within-plan Spearman correlation and by the score its pick gains over the mean candidate (the oracle's pick: the
most any scorer could gain).

The same question is put to small MLPs on the candidate's executed actions with, in turn, nothing else, the
robot's state, and the robot's state plus the objects' true positions (privileged: what a perfect read-out would
give). If the privileged scorer ranks the candidates and the robot-only one does not, which chunk wins is decided by
where the objects are, and a chooser (or a distilled policy) needs that estimate; if neither ranks them, the winner
is decided by details no such summary holds. A policy that predicts no future (action-only) gets the MLPs alone.

    .venv/bin/python scripts/future_ranking.py --policy runs/train/T/policy.pt [--candidates 8] [--lookahead 1] \
        [--seed 20000] [--episodes 60]
"""

from __future__ import annotations

import argparse
import pathlib

import torch
from lookahead_headroom import describe, run

from dust_rl.agents import load_policy, unwrap
from dust_rl.atomic_files import atomic_write
from dust_rl.search_settings import SearchSettings
from dust_rl.wm_select import VALIDATION_EVERY  # every 5th episode judges the fit, as wm_select's scorer

RIDGE = (1e-1, 1.0, 10.0, 100.0, 1000.0)
MLP_WIDTH, MLP_BATCH, MLP_STEPS = 256, 64, 300  # more steps fit the fitted plans and rank unseen ones no better
DIFFER = 0.01  # a plan ranks its candidates only where their scores differ by more than this (else: ties)


def selection_gain(predicted: torch.Tensor, scores: torch.Tensor) -> float:
    """Mean score of each plan's pick by ``predicted`` [M, K], over the mean of its candidates' scores [M, K]."""
    picked = scores.gather(1, predicted.argmax(1, keepdim=True))[:, 0]
    return (picked - scores.mean(1)).mean().item()


def spearman_within(predicted: torch.Tensor, scores: torch.Tensor) -> float:
    """Mean over plans of the rank correlation between ``predicted`` and ``scores`` across its K candidates."""
    ranks = [x.argsort(1).argsort(1).float() for x in (predicted, scores)]
    a, b = (r - r.mean(1, keepdim=True) for r in ranks)
    return ((a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-9)).mean().item()


def recorded_plans(args: argparse.Namespace) -> dict[str, torch.Tensor]:
    """Every plan of the search on the seeds, stacked: chunks [M, K, H, Da], scores [M, K], state [M, Ds],
    object_state [M, De], futures [M, K, N_o, Dv] (for a policy that predicts them) and the episode index [M]."""
    searched = torch.tensor([args.candidates, args.lookahead, args.seed, args.episodes])
    if args.cache is not None and args.cache.exists():
        plans = torch.load(args.cache, weights_only=True)
        if not torch.equal(plans["searched"], searched):
            raise SystemExit(f"{args.cache} holds the search with --candidates --lookahead --seed --episodes "
                             f"{plans['searched'].tolist()}, not {searched.tolist()}: pass those or another --cache")
        return plans
    seeds, settings = range(args.seed, args.seed + args.episodes), SearchSettings(args.candidates, args.lookahead)
    result = run(args.policy, settings, seeds, record=True)
    print(describe(settings, seeds, result))
    plans = {name: torch.stack([getattr(c, name) for c in result.choices])
             for name in ("chunks", "scores", "state", "object_state")}
    if result.choices[0].futures is not None:
        plans["futures"] = torch.stack([c.futures for c in result.choices])
    plans["episode"], plans["searched"] = torch.tensor(result.episode_of_choice), searched
    if args.cache is not None:
        with atomic_write(args.cache, "wb") as file:
            torch.save(plans, file)
    return plans


def fit_mlp(inputs: torch.Tensor, scores: torch.Tensor, fit: torch.Tensor, steps: int = MLP_STEPS) -> torch.Tensor:
    """Scores [M, K] of an MLP fitted, on the plans ``fit``, to each candidate's score relative to its plan's mean
    (inputs [M, K, D], standardised by the fitted plans)."""
    generator = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    mean, std = inputs[fit].flatten(0, 1).mean(0), inputs[fit].flatten(0, 1).std(0).clamp_min(1e-6)
    x, target = ((inputs - mean) / std).float(), (scores - scores.mean(1, keepdim=True)).float()
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[-1], MLP_WIDTH), torch.nn.GELU(),
                              torch.nn.Linear(MLP_WIDTH, MLP_WIDTH), torch.nn.GELU(), torch.nn.Linear(MLP_WIDTH, 1))
    optimiser = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-2)
    plans = fit.nonzero()[:, 0]
    for _ in range(steps):
        batch = plans[torch.randint(len(plans), (MLP_BATCH,), generator=generator)]
        predicted = net(x[batch])[..., 0]
        loss = (predicted - predicted.mean(1, keepdim=True) - target[batch]).pow(2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        return net(x)[..., 0].double()


def judge(name: str, predicted: torch.Tensor, scores: torch.Tensor, validation: torch.Tensor,
          differ: torch.Tensor) -> None:
    judged = validation & differ
    print(f"{name}: gain fitted {selection_gain(predicted[~validation], scores[~validation]):.4f}, judged "
          f"{selection_gain(predicted[validation], scores[validation]):.4f}; Spearman judged "
          f"{spearman_within(predicted[validation], scores[validation]):.3f}, on the judged plans whose scores differ "
          f"{spearman_within(predicted[judged], scores[judged]):.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--candidates", type=int, default=8)
    parser.add_argument("--lookahead", type=int, default=1)
    parser.add_argument("--seed", type=int, default=20_000)
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--cache", type=pathlib.Path,
                        help="a file for the search's plans: written after the search, read instead of searching again")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    plans = recorded_plans(args)
    scores = plans["scores"].double()  # [M, K]
    validation = plans["episode"] % VALIDATION_EVERY == VALIDATION_EVERY - 1
    differ = scores.max(1).values - scores.min(1).values > DIFFER
    oracle = selection_gain(scores[validation], scores[validation])
    print(f"{len(scores)} plans ({int(validation.sum())} judged); scores differ by more than {DIFFER} in "
          f"{differ.double().mean():.0%} of the plans ({int((validation & differ).sum())} judged); gain of the pick "
          f"over the mean candidate (judged plans): oracle {oracle:.4f}")
    executed = unwrap(load_policy(args.policy)).execute_steps
    actions = plans["chunks"][:, :, :executed].flatten(2).double()  # [M, K, E * Da]
    situation = {name: plans[name].double()[:, None].expand(-1, actions.shape[1], -1)
                 for name in ("state", "object_state")}
    for name, parts in (("MLP on the actions", [actions]),
                        ("MLP on the actions and the robot's state", [actions, situation["state"]]),
                        ("MLP on the actions, the robot's state and the true object state",
                         [actions, situation["state"], situation["object_state"]])):
        judge(name, fit_mlp(torch.cat(parts, -1), scores, ~validation & differ), scores, validation, differ)
    if "futures" not in plans:
        return
    futures = plans["futures"].flatten(2).double()  # [M, K, N_o * Dv]
    centred = futures - futures.mean(1, keepdim=True)
    spread = futures.sub(futures.mean((0, 1))).pow(2).sum(-1).mean()
    print(f"the candidates' share of the predicted futures' variance: {centred.pow(2).sum(-1).mean() / spread:.3f}")
    fit_x = centred[~validation].reshape(-1, centred.shape[-1])
    fit_y = (scores - scores.mean(1, keepdim=True))[~validation].reshape(-1)
    for ridge in RIDGE:
        weights = torch.linalg.solve(fit_x.T @ fit_x + ridge * torch.eye(fit_x.shape[1], dtype=fit_x.dtype),
                                     fit_x.T @ fit_y)
        judge(f"ridge {ridge:g} on the predicted futures", centred @ weights, scores, validation, differ)


if __name__ == "__main__":
    main()
