"""A search expert: the base policy's own chunks, chosen by looking ahead in the simulator.

Why: the methods that choose among the chunks a policy samples (steering, ``wm_select``) are bounded by what a
perfect chooser could win, and on push that bound is far above what they learnt (BENCHMARKS.md, "Search: what a
simulator chooser wins": 8 hot samples, 3 chunks of lookahead, 88% of validation layouts against the policy's
66%). The simulator can be that chooser while collecting data: at every plan the expert draws
``candidates`` chunks from the policy (at ``noise_scale`` times its trained noise), plays each one's executed part
and then ``lookahead - 1`` more of the policy's chunks from a snapshot of the simulator, scores where each lands by
the task's staged progress (the dense reward's potential; success above everything) and executes the best.
Distilling its episodes back into the policy's weights (``dust-rl finetune --method self_imitation
--search.candidates K``) is expert iteration (Anthony et al. 2017, Silver et al. 2017): policy improvement by
search, with the reward and the simulator as the model. The policy that results acts alone; the search runs only
while collecting, where the simulator can be rewound (a real robot cannot). Measured on push and pick_place: the
distilled policies kept none of the search's gain (push 56% -> 50%, or 62% trained longer where the demonstrations
alone give 68%; pick_place 22% -> 24% held-out), and scorers fitted to its rankings rank unseen plans at or near
chance even given the true object state (BENCHMARKS.md, "Search").

It plugs into the demonstration collector as the expert of
:class:`~dust_rl.envs.expert_wrapper.ExpertActionWrapper` (``dust-rl collect`` stores its actions like the scripted
expert's), so rollouts are written, resumed and finalised as any dataset. Each episode's sampling noise restarts
from its reset seed: the same seed gives the same episode.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import torch
from tensordict import TensorDict

from dust_rl.agents import DustPolicy, load_policy, unwrap
from dust_rl.agents.execution import episode_generator
from dust_rl.envs.env import FLAT_ENV_STATE_KEY, FLAT_STATE_KEY, DustEnv
from dust_rl.frozen_policy_env import observation_td
from dust_rl.search_settings import SearchSettings


@dataclasses.dataclass(frozen=True)
class Choice:
    """One plan of the search: its candidates' chunks [K, H, Da], predicted futures [K, N_o, Dv] (None for a policy
    that predicts none) and scores [K] (the one executed is ``scores.argmax()``), and the situation: the robot's
    state [Ds] and the objects' true state [De] (privileged: for diagnostics, never for the policy)."""

    chunks: torch.Tensor
    futures: torch.Tensor | None
    scores: torch.Tensor
    state: torch.Tensor
    object_state: torch.Tensor


SUCCESS_SCORE = 2.0  # above any progress (in [0, 1))
FAILURE_SCORE = -1.0  # an infeasible IK problem or diverging physics


class SearchExpert:
    """Acts for one episode of ``sim`` (built at its reset, :class:`ExpertActionWrapper`'s ``make_expert``).

    Args:
        sim: the unwrapped env (snapshots, motions without rendering, progress).
        policy: the base policy, sampling at the search's temperature.
        settings: candidates and lookahead.
        seed: the episode's reset seed; its sampling noise starts from it.
    """

    def __init__(self, sim: DustEnv, policy: DustPolicy, settings: SearchSettings, seed: int | None) -> None:
        self.sim, self.policy, self.settings = sim, policy, settings
        self.generator = episode_generator(0 if seed is None else seed)
        self.queue: list[np.ndarray] = []
        self.simulated = 0  # env steps tried from snapshots (not executed): the search's share of the sim budget
        self.choices: list[Choice] | None = None

    def act(self) -> np.ndarray:
        if not self.queue:
            self.queue = list(self.choose()[:self.policy.execute_steps].numpy())
        return self.queue.pop(0)

    def plan(self, features: TensorDict | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A chunk [H, Da] of the policy for the simulator's current state, and the future [N_o, Dv] it predicted
        with it, normalised (None for a policy that predicts none). ``features`` (:meth:`features`) lets the
        candidates of one plan share one render and one encoder pass."""
        features = self.features() if features is None else features
        out = self.policy.plan_features(features, self.generator)
        future = out.get("future_tokens", None)
        future = None if future is None else self.policy.normalizer.normalize_vision(future)[0].cpu()
        return out.get("action_chunk")[0].cpu(), future

    def features(self, observation: dict | None = None) -> TensorDict:
        """The policy's features of ``observation`` (by default the simulator's current one)."""
        observation = self.sim.observe() if observation is None else observation
        return self.policy.observation_features(observation_td(observation))

    def choose(self) -> torch.Tensor:
        """The best-scoring of ``candidates`` chunks; the simulator is left where it was. With :attr:`choices` a
        list, each plan's :class:`Choice` is appended to it."""
        observation = self.sim.observe()
        features = self.features(observation)
        chunks, futures = zip(*(self.plan(features) for _ in range(self.settings.candidates)))
        if len(chunks) == 1:
            return chunks[0]
        start = self.sim.snapshot()
        scores = []
        for chunk in chunks:
            scores.append(self.score(chunk))
            self.sim.restore(start)
        if self.choices is not None:
            self.choices.append(Choice(torch.stack(chunks), None if futures[0] is None else torch.stack(futures),
                                       torch.tensor(scores), torch.from_numpy(observation[FLAT_STATE_KEY]),
                                       torch.from_numpy(observation[FLAT_ENV_STATE_KEY])))
        return chunks[int(np.argmax(scores))]

    def score(self, chunk: torch.Tensor) -> float:
        """Play ``chunk``'s executed part and the policy's next ``lookahead - 1`` chunks; score where they land."""
        for played in range(self.settings.lookahead):
            if played:
                chunk = self.plan()[0]
            for action in chunk[:self.policy.execute_steps].numpy():
                success, reason = self.sim.advance(action)
                self.simulated += 1
                if success:
                    return SUCCESS_SCORE
                if reason == "time_limit":
                    return self.sim.progress()
                if reason:
                    return FAILURE_SCORE
        return self.sim.progress()


class SearchExpertFactory:
    """``make_expert`` for :class:`~dust_rl.envs.expert_wrapper.ExpertActionWrapper`: picklable, and each collector
    worker loads its own copy of the policy, once.

    Args:
        policy_path: the base policy's file.
        settings: the search.
    """

    def __init__(self, policy_path: pathlib.Path, settings: SearchSettings) -> None:
        self.policy_path, self.settings = pathlib.Path(policy_path), settings
        self._policy: DustPolicy | None = None

    def __call__(self, sim: DustEnv, seed: int | None) -> SearchExpert:
        return SearchExpert(sim, self.policy, self.settings, seed)

    @property
    def policy(self) -> DustPolicy:
        """The policy the search samples from, at its temperature (loaded on first use)."""
        if self._policy is None:
            policy = unwrap(load_policy(self.policy_path)).eval()
            sampler = policy.config.sampler_settings
            hotter = sampler.noise_scale * self.settings.noise_scale
            policy.set_sampler(dataclasses.replace(sampler, noise_scale=hotter))
            self._policy = policy
        return self._policy
