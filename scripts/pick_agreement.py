"""Did a distilled policy learn the search's picks? How near its chunks land to the chunk the search chose.

Why: distilling the search expert (``dust-rl finetune --method self_imitation --search.candidates K``) kept none of
its gain (BENCHMARKS.md, "Search: what a simulator chooser wins"). Either the policy cannot tell apart the situations
in which the search picks differently, or one round of fine-tuning was too little to learn the picks. Here the search
runs with the base policy on unseen seeds, and at every plan where its candidates' scores differ, each student
policy (the base, the distilled one) samples a chunk for the same observation; the script prints how often that
chunk's executed part lies nearer the search's pick than the median of the other candidates. A student that
learnt the picks is near them more often than the base, whose samples are one more draw like the candidates
(about half the time).

    .venv/bin/python scripts/pick_agreement.py --base runs/train/B/policy.pt --students runs/train/S/policy.pt \
        [--candidates 8] [--lookahead 3] [--seed 5000] [--episodes 20]
"""

from __future__ import annotations

import argparse
import pathlib

import torch
from future_ranking import DIFFER

from dust_rl.agents import load_policy, unwrap
from dust_rl.agents.execution import episode_generator
from dust_rl.env_factory import make_env
from dust_rl.frozen_policy_env import observation_td
from dust_rl.search_expert import SearchExpert, SearchExpertFactory
from dust_rl.search_settings import SearchSettings


class Examined(SearchExpert):
    """The search expert, which also asks every student for its chunk at each plan's state."""

    def __init__(self, *args, students: list, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.students, self.student_chunks = students, []
        self.student_generators = [episode_generator(i) for i in range(len(students))]

    def choose(self) -> torch.Tensor:
        observation = observation_td(self.sim.observe())
        self.student_chunks.append([student.plan_features(student.observation_features(observation), generator)
                                    .get("action_chunk")[0].cpu() for student, generator
                                    in zip(self.students, self.student_generators)])
        return super().choose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=pathlib.Path, required=True)
    parser.add_argument("--students", type=pathlib.Path, nargs="+", required=True)
    parser.add_argument("--candidates", type=int, default=8)
    parser.add_argument("--lookahead", type=int, default=3)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(1)
    factory = SearchExpertFactory(args.base, SearchSettings(args.candidates, args.lookahead))
    base = factory.policy  # searching at the trained temperature, so also the base student
    students = [base, *(unwrap(load_policy(path)).eval() for path in args.students)]
    env = make_env(base.info["env_id"], {**base.info.get("env_kwargs", {}), "task": base.info["tasks"][0]})
    nearer = torch.zeros(len(students))
    plans = 0
    steps = base.execute_steps
    for seed in range(args.seed, args.seed + args.episodes):
        env.reset(seed=seed)
        expert = Examined(env.unwrapped, base, factory.settings, seed, students=students)
        expert.choices = []
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(expert.act())
            done = terminated or truncated
        for choice, chunks in zip(expert.choices, expert.student_chunks):
            if choice.scores.max() - choice.scores.min() <= DIFFER:
                continue
            best = int(choice.scores.argmax())
            others = [k for k in range(len(choice.scores)) if k != best]
            for i, chunk in enumerate(chunks):
                distance = (choice.chunks[:, :steps] - chunk[:steps]).flatten(1).norm(dim=1)
                nearer[i] += float(distance[best] < distance[others].median())
            plans += 1
    env.close()
    for path, share in zip([args.base, *args.students], nearer / max(plans, 1)):
        print(f"{path}: nearer the search's pick than the median other candidate in {share:.0%} of {plans} plans")


if __name__ == "__main__":
    main()
