"""World-model selection, ``dust-rl finetune wm-select``: DUST's predicted future picks the chunk.

DUST samples every action chunk jointly with the frozen embedding of the
frame after it. This method puts that prediction to work without changing a
weight of the policy: it runs the base policy on its own rollouts (seeds
``rollout_seed`` on, away from the training, validation and held-out seeds),
labels each re-plan's predicted future with whether its episode succeeded,
and fits a small scorer on those pairs (:mod:`dust_rl.agents.future_scorer`;
the episodes split 4:1 into fitting and validation, the weights of the best
validation loss kept). The policy file it writes is the base policy plus the
scorer, acting with K joint samples per chunk and executing the one whose
predicted future scores best, so ``dust-rl eval`` loads it like any other
(``dust-rl eval ... resample --candidates K`` changes K; K = 1 is the base policy, bit for bit).
The base policy and each K are then evaluated with :func:`dust_rl.evaluate.closed_loop.evaluate`
on the same held-out seeds.
"""

from __future__ import annotations

import dataclasses
import time

import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy, SamplerConfig, save_policy
from dust_rl.agents.execution import replans
from dust_rl.evaluate.closed_loop import EvalConfig, eval_collector, evaluate, prepare, run_task
from dust_rl.keys import PREDICTED_FUTURE_KEY
from dust_rl.rl.config import VALIDATION_EVERY, WmSelectConfig
from dust_rl.rl.report_rows import BASE_ROW

SCORER_BATCH = 256
SCORER_LR = 1e-3
SCORER_WEIGHT_DECAY = 1e-2


@dataclasses.dataclass
class Rollouts:
    """Re-plans of the base policy's rollouts: predicted futures (normalised) [M, N_o, Dv], whether the
    episode succeeded [M], and the episode of each [M]."""

    futures: torch.Tensor
    success: torch.Tensor
    episode: torch.Tensor
    env_steps: int


def collect_rollouts(config: WmSelectConfig, task: str) -> Rollouts:
    """The base policy's own episodes on the rollout seeds, one row per re-plan."""
    seeds = range(config.rollout_seed, config.rollout_seed + config.rollouts)
    eval_config = EvalConfig(policy=config.policy, out=config.out, tasks=(task,), episodes=config.rollouts,
                             seed=config.rollout_seed, workers=1, videos=0, threads=config.threads,
                             max_steps=config.max_steps, progress=config.progress, device=config.device)
    policy, setup = prepare(eval_config)
    with (eval_collector(setup, task, policy, eval_config.worker_pool(), config.rollout_seed) as collector,
          tqdm(total=config.rollouts, desc="rollouts", disable=not config.progress) as bar):
        episodes, trajectories = run_task(collector, seeds, bar, keep=config.rollouts)
    futures, success, episode = [], [], []
    for index, record in enumerate(episodes):
        trajectory = trajectories[record.seed]
        plans = trajectory[torch.tensor([replans(t, setup.execute_steps) for t in range(record.length)])]
        futures.append(policy.standardised_future(plans.get(PREDICTED_FUTURE_KEY)))
        success.append(torch.full((plans.shape[0],), float(record.success)))
        episode.append(torch.full((plans.shape[0],), index))
    return Rollouts(torch.cat(futures), torch.cat(success), torch.cat(episode), sum(e.length for e in episodes))


def fit_scorer(policy: DustPolicy, rollouts: Rollouts, steps: int, seed: int) -> dict:
    """Fit ``policy.future_scorer`` to the rollouts' outcomes; keep the weights of the best validation loss.

    Returns:
        Rows used, the validation loss and ROC AUC of the kept weights, and the step they come from.
    """
    validation = rollouts.episode % VALIDATION_EVERY == VALIDATION_EVERY - 1
    train_x, train_y = rollouts.futures[~validation], rollouts.success[~validation]
    val_x, val_y = rollouts.futures[validation], rollouts.success[validation]
    scorer = policy.future_scorer
    optimizer = torch.optim.AdamW(scorer.parameters(), lr=SCORER_LR, weight_decay=SCORER_WEIGHT_DECAY)
    generator = torch.Generator().manual_seed(seed)
    best = {"val_loss": float("inf"), "step": 0, "state": {k: v.clone() for k, v in scorer.state_dict().items()}}
    for step in range(1, steps + 1):
        index = torch.randint(0, len(train_x), (SCORER_BATCH,), generator=generator)
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


def roc_auc(scores: torch.Tensor, labels: torch.Tensor) -> float | None:
    """Probability that a positive outranks a negative (ties count half); None without both classes."""
    positive, negative = scores[labels > 0.5], scores[labels <= 0.5]
    if not len(positive) or not len(negative):
        return None
    diff = positive[:, None] - negative[None, :]
    return ((diff > 0).float() + 0.5 * (diff == 0).float()).mean().item()


def with_scorer(policy: DustPolicy, hidden: int, candidates: int) -> DustPolicy:
    """A copy of ``policy`` (same weights) with an untrained future scorer, acting with ``candidates`` samples."""
    config = dataclasses.replace(policy.config, scorer_hidden=hidden, candidates=candidates)
    scored = DustPolicy(config, policy.backbone, policy.cameras, policy.future_camera, policy.execute_steps)
    missing, unexpected = scored.load_state_dict(policy.state_dict(), strict=False)
    if unexpected or not all(k.startswith("future_scorer.") for k in missing):
        raise RuntimeError(f"the scored copy does not hold the policy's weights (missing {missing}, "
                           f"unexpected {unexpected})")
    scored.info = dict(policy.info)
    return scored


def wm_select(config: WmSelectConfig, task: str, base: DustPolicy) -> dict:
    """Roll out, fit the scorer on a copy of ``base`` (the loaded ``config.policy``), write ``policy.pt``, evaluate
    base and each K; returns the report's parts."""
    began = time.perf_counter()
    rollouts = collect_rollouts(config, task)
    torch.manual_seed(config.seed)
    policy = with_scorer(base, config.scorer_hidden, config.candidates[0])
    scorer = fit_scorer(policy, rollouts, config.scorer_steps, config.seed)
    policy.info["wm_select"] = {"base_policy": str(config.policy), "rollout_seeds": [config.rollout_seed,
                                config.rollout_seed + config.rollouts - 1], **scorer}
    path = save_policy(policy, config.out / "policy.pt")
    trained_s = time.perf_counter() - began

    def run(policy_path, name: str, sampling: SamplerConfig) -> dict:
        return evaluate(EvalConfig(policy=policy_path, out=config.out / "eval" / name, tasks=(task,),
                                   episodes=config.eval_episodes, seed=config.eval_seed, workers=1, videos=0,
                                   threads=config.threads, max_steps=config.max_steps, sampling=sampling,
                                   progress=config.progress, device=config.device))["tasks"][0]

    sampling = base.config.sampler_settings
    rows = {BASE_ROW: run(config.policy, "base", sampling)}
    for k in config.candidates:
        rows[f"wm_select (K = {k})"] = run(path, f"k{k}", dataclasses.replace(sampling, candidates=k))
    return {"rows": rows, "train_seconds": trained_s, "rollout_env_steps": rollouts.env_steps, "scorer": scorer,
            "policy_file": str(path)}
