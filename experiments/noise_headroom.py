"""How much a policy's success depends on its sampling noise: the headroom of noise-space steering and selection.

Why: steering (``dust-rl finetune steer``) and best-of-K selection (``experiments/wm_select/``) can only choose among
what the base policy samples. If a layout fails whatever the noise, no choice of noise helps; if it succeeds under
some draws, a perfect chooser would win it. So each layout is evaluated K times with K different noise streams
(the evaluation's per-episode noise seed shifted by a large offset), and the script prints the mean success over
the draws against the share of layouts won by at least one draw: the best any noise chooser could reach.

``--branch-at C`` says where in an episode that choice matters: every draw follows the policy's own noise for its
first C chunks (so it reaches the same state, bit for bit) and its own stream from chunk C on. Draw 0 is the plain
evaluation at every C.

``--noise-scale S`` draws every chunk's initial noise S times larger (a sampling temperature; 1: as trained), so
the headroom of hotter samples is measured the same way.

``--spread K`` asks what a noise chooser controls: along the plain evaluation, each chunk is also sampled from K
other noises (the episode's own noise stream untouched), and the script prints how far apart the draws put the
gripper at the end of the chunk's executed actions (RMS distance from their mean, mm, in delta control) and how
often some draw commands the gripper otherwise than the chunk executed. A noise chooser (steering, best-of-K)
can only pick among chunks this far apart.

    .venv/bin/python experiments/noise_headroom.py --policy runs/train/T/policy.pt [--draws 4] [--branch-at 0 4 8] \
        [--spread K] [--noise-scale S] [--seed 5000] [--episodes 50]
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import torch
from in_process_eval import NOISE_OFFSET, PlanHook, add_eval_arguments, prepare_in_process

from dust_rl.agents import DustPolicy
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.evaluate.closed_loop import evaluate_task
from dust_rl.evaluate.records import wilson_interval


class BranchingNoise(PlanHook):
    """Gives draw ``draw`` the episode's own noise for its first ``branch_at`` chunks, then its own stream.

    The evaluation lends the policy the global RNG, restarted from the episode seed at every reset
    (:class:`~dust_rl.agents.execution.ChunkExecutor`); before chunk ``branch_at`` this swaps the global RNG's
    state for the draw's stream.
    """

    def __init__(self, policy: DustPolicy, branch_at: int, draw: int) -> None:
        super().__init__(policy)
        self.branch_at, self.draw = branch_at, draw
        self.seed = self.chunks = 0

    def _episode_generator(self, seed: int) -> torch.Generator:
        self.seed, self.chunks = int(seed), 0
        return self.unshifted(seed)

    def _plan_features(self, *args, **kwargs):
        if self.draw and self.chunks == self.branch_at:
            torch.set_rng_state(self.unshifted(self.seed + self.draw * NOISE_OFFSET).get_state())
        self.chunks += 1
        return self.plan_features(*args, **kwargs)


class NoiseSpread(PlanHook):
    """Records, at every plan of the evaluation, how far ``draws`` other noises move the chunk's executed part.

    The extra samples draw from their own generators, so the episode (its noise stream included) is the plain
    evaluation's. Rows of :attr:`rows`: (RMS spread of the executed end point in mm, the executed gripper command
    closed, some draw's gripper command differs in sign from the executed one on an executed step).
    """

    def __init__(self, policy: DustPolicy, draws: int) -> None:
        super().__init__(policy)
        self.draws = draws
        self.rows: list[tuple[float, bool, bool]] = []

    def _plan_features(self, features, generator=None, action_noise=None):
        out = self.plan_features(features, generator, action_noise)
        steps = self.policy.execute_steps
        executed = out["action_chunk"][:, :steps]
        others = [self.plan_features(features, torch.Generator().manual_seed(len(self.rows) * self.draws + d))
                  ["action_chunk"][:, :steps] for d in range(self.draws)]
        chunks = torch.cat([executed, *others])  # [1 + K, steps, Da]
        ends = chunks[..., :3].clamp(-1, 1).sum(1) * MAX_TRANSLATION * 1000  # mm from where the chunk starts
        spread = float((ends - ends.mean(0)).square().sum(-1).mean().sqrt())
        flips = bool((torch.sign(chunks[1:, :, -1]) != torch.sign(executed[:, :, -1])).any())
        self.rows.append((spread, bool(executed[0, -1, -1] > 0), flips))
        return out


def print_spread(policy: DustPolicy, setup, config, draws: int) -> None:
    """The ``--spread`` table: the chunks' noise spread, all of them and those executed with the gripper closed."""
    with NoiseSpread(policy, draws) as spread:
        wins = sum(e.success for task in setup.tasks for e in evaluate_task(setup, task, policy, config)[0])
    rows = torch.tensor(spread.rows, dtype=torch.float64)
    print(f"{config.policy}, seeds {config.seed}..{config.seed + config.episodes - 1} ({wins} successes), "
          f"{draws} other noises per chunk:\n\n| chunks | n | spread of the end point, mm: median | 90% | max "
          f"| some draw flips the gripper |\n|---|---|---|---|---|---|")
    for name, mask in (("all", rows[:, 0] >= 0), ("gripper closed", rows[:, 1] > 0), ("gripper open", rows[:, 1] == 0)):
        part = rows[mask]
        if len(part):
            q = torch.quantile(part[:, 0], torch.tensor([0.5, 0.9], dtype=torch.float64))
            print(f"| {name} | {len(part)} | {q[0]:.2f} | {q[1]:.2f} | {part[:, 0].max():.2f} | "
                  f"{int(part[:, 2].sum())} ({part[:, 2].mean():.0%}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser)
    parser.add_argument("--draws", type=int, default=4, help="noise streams per layout (K)")
    parser.add_argument("--branch-at", type=int, nargs="+", default=[0],
                        help="chunks every draw shares with the policy's own noise before its stream starts")
    parser.add_argument("--spread", type=int, default=0, metavar="K",
                        help="instead: the spread of K other noises' chunks along the plain evaluation (module doc)")
    parser.add_argument("--noise-scale", type=float, default=1.0, metavar="S",
                        help="scale of the initial action noise, a sampling temperature (1: as trained)")
    args = parser.parse_args()
    finite_scale = math.isfinite(args.noise_scale) and args.noise_scale >= 0
    if args.draws < 1 or min(args.branch_at) < 0 or args.spread < 0 or not finite_scale:
        parser.error("--draws needs K >= 1, --branch-at chunk counts >= 0, --spread K >= 0, "
                     "--noise-scale a finite S >= 0")
    policy, setup, config = prepare_in_process(args)
    policy.set_sampler(dataclasses.replace(policy.config.sampler_settings, noise_scale=args.noise_scale))
    if args.spread:
        print_spread(policy, setup, config, args.spread)
        return
    for branch_at in args.branch_at:
        wins = torch.zeros(args.draws, len(setup.tasks), args.episodes, dtype=torch.bool)
        for draw in range(args.draws):
            with BranchingNoise(policy, branch_at, draw):
                for t, task in enumerate(setup.tasks):
                    episodes, _, _, _ = evaluate_task(setup, task, policy, config)
                    wins[draw, t] = torch.tensor([e.success for e in episodes])
            print(f"branch at chunk {branch_at}, draw {draw}: {int(wins[draw].sum())}/{wins[draw].numel()}",
                  flush=True)
        mean, best = int(wins.sum()), int(wins.any(0).sum())
        n = wins[0].numel()
        low, high = wilson_interval(best, n)
        print(f"{args.policy}, seeds {args.seed}..{args.seed + args.episodes - 1}, {args.draws} noise draws per "
              f"layout (initial noise x{args.noise_scale:g}) from chunk {branch_at} on: mean success "
              f"{mean / (args.draws * n):.0%}; layouts won by at least one draw {best}/{n} ({best / n:.0%}, "
              f"95% CI {low:.0%}-{high:.0%}); won by every draw "
              f"{int(wins.all(0).sum())}/{n}", flush=True)


if __name__ == "__main__":
    main()
