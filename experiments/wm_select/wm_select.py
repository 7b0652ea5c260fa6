"""World-model selection: DUST's predicted future picks the chunk, among K joint samples, by a scorer of futures.

Why: DUST samples every action chunk jointly with the frozen embedding of the frame after it. Drawing K joint
samples and executing the one whose predicted future looks most like success would use the world model at test
time without changing a weight of the policy. Measured (docs/results/2026-11-24-rl-finetuning-first-runs.md): on
press_button (600 demonstrations, 20% held-out) K = 4 gave 18% and K = 8 12%; on pick_place (the DUST image policy,
26%) 28% and 24%. The scorer tells a re-plan of a succeeding episode from one of a failing episode (validation ROC
AUC 0.70 and 0.80), but it learnt the situation, not which of K samples of one situation succeeds, so choosing
among them gains nothing. This was ``dust-rl finetune wm-select`` (the scorer and K stored in the policy file, the
selection inside ``DustPolicy``) until commit 74cb2e1, where those runs reproduce; policy files written by it no
longer load (``scorer_hidden`` and ``candidates`` are retired settings).

The study, against the package as it is: the base policy runs on its own rollouts (seeds ``--rollout-seed`` on,
away from the training, validation and held-out seeds) through ``dust-rl eval``'s runner; each re-plan's predicted
future (standardised, as the world model's targets) is labelled with whether its episode succeeded; a small MLP
(:class:`FutureScorer`) is fitted on those pairs, the episodes split 4:1 into fitting and validation and the
weights of the best validation loss kept (written to ``scorer.pt``). The base policy and, for each K, the policy
acting on the best of K joint samples by that scorer (:class:`BestOfK`; K = 1 is the base policy, bit for bit)
are evaluated on the same held-out seeds, in this process (one env), and compared episode by episode
(``report.json``, ``report.md``).

    .venv/bin/python experiments/wm_select/wm_select.py --policy runs/train/pb600/policy.pt \
        --out runs/ft/pb600_wm_select --rollouts 200 --candidates 4 8 --eval-episodes 50 --eval-seed 10000
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from typing import NamedTuple

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.agents.execution import replans
from dust_rl.data.seeding import HELDOUT_SEED
from dust_rl.evaluate.closed_loop import EvalConfig, eval_collector, eval_setup, evaluate, run_task
from dust_rl.evaluate.records import Episode
from dust_rl.keys import FUTURE_TOKENS_KEY, PREDICTED_FUTURE_KEY
from dust_rl.rl.config import ROLLOUT_SEED
from dust_rl.rl.report_rows import BASE_ROW, rows_against_base
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.runtime.settings import RuntimeSettings

VALIDATION_EVERY = 5  # every 5th rollout episode validates the scorer
SCORER_BATCH = 256
SCORER_LR = 1e-3
SCORER_WEIGHT_DECAY = 1e-2
SCORER_FILE = "scorer.pt"


class FutureScorer(nn.Module):
    """Predicted future tokens [B, N_o, Dv] (standardised frames) to a logit [B] of "this chunk leads to success".

    Args:
        n_tokens: N_o.
        dim: Dv.
        hidden: width of the hidden layer.
    """

    def __init__(self, n_tokens: int, dim: int, hidden: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Flatten(), nn.LayerNorm(n_tokens * dim), nn.Linear(n_tokens * dim, hidden),
                                 nn.GELU(), nn.Linear(hidden, 1))

    def forward(self, future_tokens: Tensor) -> Tensor:
        return self.mlp(future_tokens).squeeze(-1)


class BestOfK:
    """Inside a ``with`` block, ``policy`` (one that predicts the future) acts on the best of ``candidates`` joint
    samples per observation: the one whose predicted future ``scorer`` rates best (every plan, :meth:`DustPolicy.plan`
    and the executor's, passes through here; leaving the block restores the policy's own planning).

    The K samples of an observation are drawn side by side in one batch, so they are the samples of planning the
    observation K times. The evaluation's runner gives no initial noise (steering does, and is another method).
    """

    def __init__(self, policy: DustPolicy, scorer: FutureScorer, candidates: int) -> None:
        self.policy, self.scorer, self.candidates = policy, scorer, candidates

    def __enter__(self) -> BestOfK:
        self.plan_features = self.policy.plan_features
        self.policy.plan_features = self._plan_features
        return self

    def __exit__(self, *exc: object) -> None:
        del self.policy.plan_features  # the class's method again

    @torch.no_grad()
    def _plan_features(self, features: TensorDictBase, generator: torch.Generator | None = None,
                       action_noise: Tensor | None = None, vision_noise: Tensor | None = None) -> TensorDict:
        k = self.candidates
        if k == 1:
            return self.plan_features(features, generator, action_noise, vision_noise)
        if action_noise is not None or vision_noise is not None:
            raise ValueError("best-of-K draws its own initial noises")
        n = features.batch_size[0]
        rows = torch.arange(n, device=features.device).repeat_interleave(k)
        out = self.plan_features(features[rows], generator)
        scores = self.scorer(self.policy.standardised_future(out.get(FUTURE_TOKENS_KEY))).view(n, k)
        return out.view(n, k)[torch.arange(n, device=scores.device), scores.argmax(-1)]


class Rollouts(NamedTuple):
    """Re-plans of the base policy's rollouts: predicted futures (standardised) [M, N_o, Dv], whether the episode
    succeeded [M], and the episode of each [M]."""

    futures: Tensor
    success: Tensor
    episode: Tensor
    env_steps: int


def collect_rollouts(policy: DustPolicy, config: EvalConfig) -> Rollouts:
    """The base policy's own episodes of ``config`` (its one task, one local worker), one row per re-plan."""
    setup = eval_setup(config, policy)
    task, seeds = setup.tasks[0], range(config.seed, config.seed + config.episodes)
    with (eval_collector(setup, task, policy, config.worker_pool(), config.seed) as collector,
          tqdm(total=config.episodes, desc="rollouts", disable=not config.runtime.progress) as bar):
        episodes, trajectories = run_task(collector, seeds, bar, keep=config.episodes)
    futures, success, episode = [], [], []
    for index, record in enumerate(episodes):
        trajectory = trajectories[record.seed]
        plans = trajectory[torch.tensor([replans(t, setup.execute_steps) for t in range(record.length)])]
        futures.append(policy.standardised_future(plans.get(PREDICTED_FUTURE_KEY).to(policy.weights_device)))
        success.append(torch.full((plans.shape[0],), float(record.success), device=policy.weights_device))
        episode.append(torch.full((plans.shape[0],), index, device=policy.weights_device))
    return Rollouts(torch.cat(futures), torch.cat(success), torch.cat(episode), sum(e.length for e in episodes))


def fit_scorer(scorer: FutureScorer, rollouts: Rollouts, steps: int, seed: int) -> dict:
    """Fit ``scorer`` to the rollouts' outcomes; keep the weights of the best validation loss.

    Returns:
        Rows used, the validation loss and ROC AUC of the kept weights, and the step they come from.
    """
    validation = rollouts.episode % VALIDATION_EVERY == VALIDATION_EVERY - 1
    train_x, train_y = rollouts.futures[~validation], rollouts.success[~validation]
    val_x, val_y = rollouts.futures[validation], rollouts.success[validation]
    optimizer = torch.optim.AdamW(scorer.parameters(), lr=SCORER_LR, weight_decay=SCORER_WEIGHT_DECAY)
    generator = torch.Generator().manual_seed(seed)
    best = {"val_loss": float("inf"), "step": 0, "state": {k: v.clone() for k, v in scorer.state_dict().items()}}
    for step in range(1, steps + 1):
        index = torch.randint(0, len(train_x), (SCORER_BATCH,), generator=generator).to(train_x.device)
        loss = F.binary_cross_entropy_with_logits(scorer(train_x[index]), train_y[index])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            val_loss = F.binary_cross_entropy_with_logits(scorer(val_x), val_y).item()
        if val_loss < best["val_loss"]:
            best = {"val_loss": val_loss, "step": step, "state": {k: v.clone() for k, v in scorer.state_dict().items()}}
    scorer.load_state_dict(best["state"])
    with torch.no_grad():
        auc = roc_auc(scorer(val_x), val_y)
    return {"train_rows": len(train_x), "validation_rows": len(val_x), "validation_loss": best["val_loss"],
            "validation_auc": auc, "kept_step": best["step"], "success_fraction": rollouts.success.mean().item()}


def roc_auc(scores: Tensor, labels: Tensor) -> float | None:
    """Probability that a positive outranks a negative (ties count half); None without both classes."""
    positive, negative = scores[labels > 0.5], scores[labels <= 0.5]
    if not len(positive) or not len(negative):
        return None
    diff = positive[:, None] - negative[None, :]
    return ((diff > 0).float() + 0.5 * (diff == 0).float()).mean().item()


def markdown(report: dict) -> str:
    fit = report["scorer"]
    auc = "n/a" if fit["validation_auc"] is None else f"{fit['validation_auc']:.2f}"
    lines = [f"# World-model selection: {report['policy']}", "",
             f"- task `{report['task']}`: a future scorer fitted on {report['rollouts']} base-policy rollouts "
             f"({report['rollout_env_steps']} env steps, {report['train_seconds']:.0f} s; validation ROC AUC {auc})",
             f"- seeds {report['seeds'][0]}..{report['seeds'][1]}; the policy's weights unchanged", "",
             "| policy | episodes | success | 95% CI | episodes won / lost against the base (McNemar p) |",
             "|---|---|---|---|---|"]
    for row in report["rows"]:
        paired = row.get("vs_base")
        versus = "" if paired is None else f"+{paired['gained']} / -{paired['lost']} (p = {paired['p_value']:.2f})"
        lines.append(f"| {row['task']} | {row['episodes']} | {100 * row['success_rate']:.0f}% | "
                     f"{100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}% | {versus} |")
    return "\n".join([*lines, "", "Reproduce:", "", f"    {report['command']}", ""])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=pathlib.Path, required=True, help="policy file written by dust-rl train")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/wm_select"))
    parser.add_argument("--task", help="default: the policy's first training task")
    parser.add_argument("--candidates", type=int, nargs="+", default=[4, 8], help="the K values evaluated")
    parser.add_argument("--rollouts", type=int, default=100, help="base-policy episodes the scorer is fitted on")
    parser.add_argument("--rollout-seed", type=int, default=ROLLOUT_SEED, help="first seed of the rollouts")
    parser.add_argument("--scorer-hidden", type=int, default=128, help="hidden width of the scorer")
    parser.add_argument("--scorer-steps", type=int, default=2000,
                        help="scorer optimiser steps (the weights of the best validation loss are kept)")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--eval-seed", type=int, default=HELDOUT_SEED)
    parser.add_argument("--seed", type=int, default=0, help="the scorer's initial weights and batches")
    parser.add_argument("--max-steps", type=int, help="time limit per episode; default: the task's")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--no-progress", dest="progress", action="store_false")
    args = parser.parse_args(argv)
    if (min(args.candidates) < 1 or args.rollouts < VALIDATION_EVERY or min(args.scorer_hidden, args.scorer_steps) < 1
            or min(args.rollout_seed, args.seed) < 0):
        parser.error(f"--candidates need K >= 1, --rollouts at least {VALIDATION_EVERY} (every {VALIDATION_EVERY}th "
                     "episode validates the scorer), --scorer-hidden and --scorer-steps >= 1, seeds >= 0")
    return args


def main(argv: list[str] | None = None) -> dict:
    """Roll out, fit the scorer, evaluate the base and each K on the held-out seeds; returns the report."""
    args = parse_args(argv)
    with torch_threads(args.threads):
        policy = load_policy(args.policy).to(resolve_device(args.device))
        task = args.task or (policy.info.get("tasks") or [None])[0]
        if task is None:
            raise SystemExit(f"{args.policy} records no training task: give --task")
        if not policy.config.has_vision or policy.config.sampler_name == "action_only":
            raise SystemExit(f"{args.policy} predicts no future to score (action-only variant or sampler)")

        def config(out: pathlib.Path, episodes: int, seed: int) -> EvalConfig:
            return EvalConfig(policy=args.policy, out=out, tasks=(task,), episodes=episodes, seed=seed, workers=1,
                              videos=0, max_steps=args.max_steps,
                              runtime=RuntimeSettings(threads=args.threads, device=args.device, progress=args.progress))

        began = time.perf_counter()
        rollouts = collect_rollouts(policy, config(args.out / "rollouts", args.rollouts, args.rollout_seed))
        torch.manual_seed(args.seed)
        scorer = FutureScorer(policy.config.n_vision_tokens, policy.config.vision_dim, args.scorer_hidden)
        fit = fit_scorer(scorer.to(policy.weights_device), rollouts, args.scorer_steps, args.seed)
        scorer.eval()
        args.out.mkdir(parents=True, exist_ok=True)
        torch.save({"hidden": args.scorer_hidden, "state_dict": scorer.state_dict(), "fit": fit},
                   args.out / SCORER_FILE)  # FutureScorer(N_o, Dv, hidden).load_state_dict(...) reads it back
        trained_s = time.perf_counter() - began
        rows = {BASE_ROW: evaluate(config(args.out / "eval" / "base", args.eval_episodes, args.eval_seed),
                                   policy=policy)}
        for k in args.candidates:
            with BestOfK(policy, scorer, k):
                held_out = config(args.out / "eval" / f"k{k}", args.eval_episodes, args.eval_seed)
                rows[f"wm_select (K = {k})"] = evaluate(held_out, policy=policy,
                                                        about={"wm_select": {"candidates": k, **fit}})
    episodes = {name: [Episode.from_json(e) for e in row["tasks"][0]["per_episode"]] for name, row in rows.items()}
    command = ["python", "experiments/wm_select/wm_select.py", *(sys.argv[1:] if argv is None else argv)]
    report = {"policy": str(args.policy), "task": task, "command": " ".join(command),
              "rollouts": args.rollouts, "rollout_seeds": [args.rollout_seed, args.rollout_seed + args.rollouts - 1],
              "rollout_env_steps": rollouts.env_steps, "scorer": fit, "train_seconds": trained_s,
              "seeds": [args.eval_seed, args.eval_seed + args.eval_episodes - 1],
              "rows": rows_against_base(episodes),
              "per_episode": {name: [e.to_json() for e in kept] for name, kept in episodes.items()}}
    (args.out / "report.json").write_text(json.dumps(report, indent=2))
    (args.out / "report.md").write_text(markdown(report))
    for row in report["rows"]:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful ({100 * row['success_rate']:.0f}%, "
              f"95% CI {100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}%)")
    return report


if __name__ == "__main__":
    main()
