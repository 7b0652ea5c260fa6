"""How well a DUST policy's world model predicts the future it acts in, in closed loop.

Why: DUST's claim is that the jointly sampled future (the t+H tokens of ``future_camera``) makes the actions
better. If the predicted future is no closer to what the camera then shows than the present frame is, the
actions cannot draw anything from it. Along a plain evaluation, every plan's predicted future is compared with
the tokens the camera gives H env steps later (the plan ``H / execute_steps`` re-plans on; the chunk executed
in between is the first ``execute_steps`` actions of each plan, not the whole predicted one), beside two
baselines: the present frame's tokens (nothing moves) and the targets' own mean (nothing known). Errors are
mean squares in the policy's normalised token units, so 1 is about the variance of a token.

One sampled future is a draw from what the model thinks may happen: even a perfectly calibrated model's draw
misses the truth by twice its uncertainty's variance, where the mean of its draws misses by once. ``--samples K``
also draws K - 1 more futures per plan (from their own generator: the actions, and so the episode, stay those
of a plain evaluation) and scores the mean of the K, the model's estimate of the expected future.

    .venv/bin/python experiments/world_model_error.py \
        --policy runs/bench/press_button/train/dust_seed0_demos200/policy.pt [--seed 5000] [--episodes 20] [--samples 8]
"""

from __future__ import annotations

import argparse

import torch
from in_process_eval import NOISE_OFFSET, PlanHook, add_eval_arguments, prepare_in_process

from dust_rl.agents import DustPolicy
from dust_rl.evaluate.closed_loop import evaluate_task


class FutureRecorder(PlanHook):
    """Records, per episode, each plan's observed tokens and predicted future (the evaluation itself unchanged)."""

    def __init__(self, policy: DustPolicy, samples: int = 1) -> None:
        super().__init__(policy)
        self.samples = samples
        self.extra = torch.Generator(policy.weights_device)  # the further draws' own noise
        self.episodes: list[list[tuple[torch.Tensor, torch.Tensor]]] = []

    def _episode_generator(self, seed: int) -> torch.Generator:
        self.episodes.append([])
        self.extra.manual_seed(int(seed) + NOISE_OFFSET)  # not the episode's stream: no draw repeats the acting one
        return self.unshifted(seed)

    def _plan_features(self, features, generator=None, action_noise=None):
        out = self.plan_features(features, generator, action_noise)
        futures = [out["future_tokens"][0]] + [self.plan_features(features, self.extra)["future_tokens"][0]
                                               for _ in range(self.samples - 1)]
        self.episodes[-1].append((features["image_tokens"][0], torch.stack(futures)))
        return out


def errors(policy: DustPolicy, episodes: list[list[tuple[torch.Tensor, torch.Tensor]]]) -> dict[str, float]:
    """Mean squared errors (normalised units) of the world model (the acting draw, and the mean of every draw when
    there are several), the present frame and the targets' mean."""
    ahead = policy.config.horizon // policy.execute_steps
    predicted, present, target = [], [], []
    for plans in episodes:
        seen = [policy.future_targets(tokens) for tokens, _ in plans]  # each plan's frame, as a world-model target
        for k in range(len(plans) - ahead):
            predicted.append(plans[k][1])
            present.append(seen[k])
            target.append(seen[k + ahead])
    if not target:
        raise SystemExit("no episode lasted long enough to compare a predicted future with the real one")
    predicted, present, target = (policy.normalizer.normalize_vision(torch.stack(x)).double()
                                  for x in (predicted, present, target))  # predicted: [plans, K, N_o, Dv]
    row = {"plans": len(target), "world model": float((predicted[:, 0] - target).square().mean())}
    if predicted.shape[1] > 1:
        row[f"mean of {predicted.shape[1]} draws"] = float((predicted.mean(1) - target).square().mean())
    return row | {"present frame": float((present - target).square().mean()),
                  "targets' mean": float((target - target.mean(0)).square().mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)
    parser.add_argument("--samples", type=int, default=1, help="futures drawn per plan (module doc)")
    args = parser.parse_args()
    if args.samples < 1:
        parser.error(f"--samples must be at least 1, got {args.samples}")
    policy, setup, config = prepare_in_process(args)
    if not policy.writes_future:
        parser.error(f"{args.policy} predicts no future (variant {policy.config.variant!r})")
    if policy.config.horizon % policy.execute_steps:
        parser.error(f"the horizon ({policy.config.horizon}) is not a whole number of re-plans "
                     f"({policy.execute_steps} steps each), so no plan sees the frame at t+H")
    with FutureRecorder(policy, args.samples) as recorder:
        wins = sum(e.success for task in setup.tasks for e in evaluate_task(setup, task, policy, config)[0])
    row = errors(policy, recorder.episodes)
    plans = row.pop("plans")
    print(f"{args.policy}, seeds {args.seed}..{args.seed + args.episodes - 1} ({wins} successes), {plans} plans "
          f"compared with the frame H = {policy.config.horizon} steps on (MSE, normalised tokens): "
          + " | ".join(f"{name} {value:.3f}" for name, value in row.items()))


if __name__ == "__main__":
    main()
