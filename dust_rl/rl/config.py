"""``dust-rl finetune``'s settings, apart from the methods that read them so each method's module can import them."""

from __future__ import annotations

import dataclasses
import math
import pathlib
from dataclasses import dataclass, field
from typing import Literal

from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED
from dust_rl.errors import ConfigError, check_at_least, check_finite
from dust_rl.keys import EXPERT_ACTION_KEY
from dust_rl.runtime.device import resolve_device
from dust_rl.train.imitation import TrainSettings

VALIDATION_EVERY = 5  # every 5th rollout episode validates the scorer
RL_AGENT_KIND = "dust-rl rl agent"
# rounds: a finished self_imitation run resumed with more rounds goes on from its last round.
RESUMABLE_FIELDS = ("resume", "progress", "threads", "rounds", "control")
# PPO keeps no replay buffer sized by the run, so a resumed PPO run may also be given a larger budget.
PPO_RESUMABLE_FIELDS = (*RESUMABLE_FIELDS, "steps")
# Settings only one algorithm reads: set away from their defaults with the other, they are refused.
ALGORITHM_SETTINGS = {"sac": ("gradient_steps", "target_entropy", "q_bounds"),
                      "ppo": ("n_steps", "n_epochs", "target_kl", "critic_warmup")}


@dataclass
class FinetuneConfig:
    """RL fine-tuning of a trained DUST policy (frozen, except with self_imitation, which writes a new one)."""

    policy: pathlib.Path
    """Policy file written by ``dust-rl train``."""
    out: pathlib.Path = pathlib.Path("runs/finetune")
    """Run folder: ``config.json``, ``checkpoints/``, ``rl_agent.pt``, ``report.json``, ``report.md`` and ``logs/``
    (SB3's scalars: CSV, TensorBoard)."""
    method: Literal["steer", "residual", "wm_select", "self_imitation"] = "steer"
    """``steer``: the RL action is the policy's initial action noise, one step per chunk (DSRL);
    ``residual``: a bounded correction added to every executed action; ``wm_select``: K joint samples per chunk,
    the one whose predicted future a scorer fitted on the policy's own rollouts rates best executed
    (:mod:`dust_rl.rl.wm_select`; writes ``policy.pt``, no SB3 agent); ``self_imitation``: the policy fine-tuned on
    its demonstrations and its own successful rollouts, round after round (:mod:`dust_rl.rl.self_imitation`; each
    round writes a ``policy.pt``, no SB3 agent)."""
    algorithm: Literal["sac", "ppo"] = "sac"
    """stable-baselines3 algorithm (``MultiInputPolicy``)."""
    steps: int = 20_000
    """RL agent steps (chunks when steering, env steps for residual)."""
    task: str | None = None
    """Task to fine-tune on; default: the policy's first training task."""
    reward: Literal["sparse", "dense"] = "sparse"
    """The env's reward while training: 1 on success only, or that plus potential-based shaping by the task's
    staged progress, shaped for ``gamma`` (``DustEnv.step``; evaluation counts successes either way)."""
    gamma: float = 0.99
    """The RL agent's discount per RL step (an env step for residual, a chunk when steering; steering discounts
    the rewards within a chunk by ``gamma ** (1 / execute_steps)`` per env step, the discount the dense reward is
    then shaped for)."""
    finite_horizon: bool = False
    """The time limit ends an episode as a failure for the RL agent (terminated: nothing is bootstrapped past it)
    and the agent observes the fraction of the episode left (:mod:`dust_rl.rl.frozen_policy_env`). Default: a
    time-limit end is a truncation, bootstrapped as if the episode went on."""
    noise_bound: float = 2.0
    """Steering: the noise magnitude an RL action of +-1 maps to."""
    residual_scale: float = 0.1
    """Residual: what an RL action of +-1 adds, as a fraction of the action box's half-width."""
    world_model_obs: bool = False
    """Residual: the RL agent (actor and critic) also sees the future DUST sampled jointly with the chunk being
    executed (:mod:`dust_rl.rl.residual`); needs a policy that predicts one."""
    learning_starts: int = 1000
    """SAC: steps before the first update (uniformly random actions, unless ``initial_std`` is set)."""
    gradient_steps: int = 1
    """SAC: gradient steps per RL step, the update-to-data ratio (DSRL: 20)."""
    target_entropy: float | None = None
    """SAC: learn the entropy coefficient so the policy keeps this entropy (SB3's ``ent_coef="auto"``; DSRL: 0),
    starting from ``initial_alpha``; with ``initial_std`` the std then starts there and is learnt. None: SB3's
    target (minus the action dimension), or with ``initial_std`` a fixed std and no entropy bonus
    (:mod:`dust_rl.rl.start_at_base`)."""
    initial_alpha: float = 1.0
    """SAC: the entropy coefficient's start when it is learnt (SB3's 1.0). Each step's entropy bonus is about alpha
    times the action dimension (112 when steering stack) against a sparse reward of 1, so a steering run with
    ``target_entropy`` wants it far smaller."""
    initial_std: float | None = None
    """Start the RL agent at the base policy (:mod:`dust_rl.rl.start_at_base`): mean action 0 (no residual; steering:
    the centre of the base policy's noise) and this exploration standard deviation (SAC: before the tanh), acting so
    from the first step, the std fixed (SAC: no entropy bonus). None: SB3's initialisation (random mean, std ~1 and
    learnt, uniformly random warm-up)."""
    batch_size: int = 256
    """SAC/PPO minibatch size."""
    learning_rate: float = 3e-4
    """SAC/PPO optimiser step size (SB3's default)."""
    n_steps: int = 2048
    """PPO: RL steps per rollout, i.e. between updates (SB3's default; at most ``steps``). Steering takes one RL
    step per chunk, so a rollout holds ``execute_steps`` times as many env steps."""
    n_epochs: int = 10
    """PPO: passes over each rollout (SB3's default)."""
    target_kl: float | None = None
    """PPO: end a rollout's epochs early once the policy's approximate KL from the rollout's exceeds 1.5 times
    this (SB3's ``target_kl``): SB3 normalises advantages, so each update is full-sized however weak the signal;
    this bounds how far one rollout moves the policy. None: no limit."""
    critic_warmup: int = 0
    """PPO: env steps (whole rollouts) during which only the critic learns and the actor stays at the base policy,
    so the first actor updates follow advantages from a fitted value function instead of a random one."""
    net_arch: tuple[int, ...] = (256, 256)
    """Hidden layers of the RL actor and critic."""
    layer_norm: bool = False
    """Normalise each hidden layer of the RL actor and critic before its ReLU (:mod:`dust_rl.rl.critic_limits`: caps
    how far the critic's Q extrapolates to actions the actor has not tried; DSRL's setting). PPO's MLPs then use
    ReLU instead of their default tanh."""
    q_bounds: tuple[float, float] | None = None
    """SAC: squash the critic's output into (LO, HI), the returns the reward can pay (sparse: 0 1;
    :mod:`dust_rl.rl.critic_limits`). None: unbounded."""
    seed: int = 0
    """Seed of the RL agent, and reset seed of the first training episode (later ones follow the env's RNG)."""
    eval_episodes: int = 20
    """Closed-loop episodes of the base and the fine-tuned policy, on seeds eval_seed, eval_seed + 1, ..."""
    eval_seed: int = HELDOUT_SEED
    """First evaluation seed (training data: 0 on; validation: 5000 on; held-out: 10000 on)."""
    max_steps: int | None = None
    """Time limit per episode in env steps; default: the task's."""
    candidates: tuple[int, ...] = (4, 8)
    """wm_select: the K values evaluated; the written ``policy.pt`` acts with the first."""
    rollouts: int = 100
    """wm_select: base-policy episodes whose outcomes train the scorer."""
    rollout_seed: int = 20_000
    """wm_select, self_imitation: first seed of the rollouts (away from training, validation and held-out seeds;
    self_imitation's round r starts 10,000 seeds further on per round)."""
    rounds: int = 1
    """self_imitation: rounds of rollouts and fine-tuning (``--resume`` with more rounds extends a run)."""
    rollout_successes: int = 150
    """self_imitation: successful rollouts each round collects (its failures are stored only for DAgger,
    ``--train.extra-action-key expert_action``)."""
    demos: pathlib.Path | None = None
    """self_imitation: the demonstrations fine-tuning keeps training on; default: the policy's training dataset
    (``info["dataset"]``)."""
    train: TrainSettings = field(default_factory=lambda: TrainSettings(steps=3000, lr=1e-4))
    """self_imitation: how each round fine-tunes (``--train.steps``, ``--train.lr``, ``--train.extra-fraction``,
    ``--train.start-rows`` ...; ``--train.extra-action-key expert_action``: DAgger); the starting policy, the
    rollouts, threads and device are the round's."""
    control: bool = True
    """self_imitation: also fine-tune the base policy on its demonstrations alone, for as many steps as all rounds
    together, and report it as a row: the gain a method is credited with is the one above that control (on push the
    demonstrations alone gave 68% held-out where a search distillation gave 62%: docs/results)."""
    scorer_hidden: int = 128
    """wm_select: hidden width of the scorer."""
    scorer_steps: int = 2000
    """wm_select: scorer optimiser steps (the weights of the best validation loss are kept)."""
    eval_every: int = 0
    """RL steps between evaluations of the agent on ``curve_episodes`` validation episodes, for the learning curve
    (``learning_curve.json``/``.png``: success against env steps, from the base policy at 0); 0: none."""
    curve_episodes: int = 10
    """Episodes of each periodic evaluation."""
    curve_seed: int = VALIDATION_SEED
    """First seed of the periodic evaluations (validation seeds: the held-out ones stay for the report)."""
    checkpoint_every: int = 5000
    """RL steps between checkpoints of the whole learning state (one is always written at the end; PPO rounds
    each sitting up to whole rollouts of ``n_steps``)."""
    resume: bool = False
    """Continue the run in ``out`` from its newest checkpoint (a PPO run, also with a larger ``steps``: a finished
    run goes on to the new budget; SAC's replay buffer is sized by the original one)."""
    threads: int = 1
    """torch threads."""
    device: str = "auto"
    """Where the frozen DUST policy and the SB3 agent run (:mod:`dust_rl.runtime.device`): auto, cpu, cuda, cuda:N, mps;
    the envs run on the CPU (wm_select: its rollouts and evaluations run the policy there, the scorer fits on the
    CPU)."""
    progress: bool = True
    """Show progress bars."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "steps", "batch_size", "eval_episodes", "threads", "max_steps", "checkpoint_every",
                       "rollouts", "scorer_hidden", "scorer_steps", "rounds", "rollout_successes")
        check_at_least(self, 0, "learning_starts", "seed", "eval_seed", "rollout_seed", "eval_every", "curve_seed")
        check_at_least(self, 1, "curve_episodes")
        if not self.candidates or min(self.candidates) < 1:
            raise ConfigError(f"candidates must list positive sample counts, got {self.candidates}")
        if self.method == "wm_select" and self.rollouts < VALIDATION_EVERY:
            raise ConfigError(f"wm_select needs rollouts >= {VALIDATION_EVERY}: every {VALIDATION_EVERY}th episode "
                              "validates the scorer")
        check_finite(self, "noise_bound", "residual_scale", "learning_rate", positive=True)
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"gamma must be a discount factor in (0, 1], got {self.gamma}")
        if self.world_model_obs and self.method != "residual":
            raise ConfigError(f"world_model_obs applies to --method residual, not {self.method}")
        if self.initial_std is not None:
            check_finite(self, "initial_std", positive=True)
        check_at_least(self, 1, "gradient_steps", "n_steps", "n_epochs")
        check_at_least(self, 0, "critic_warmup")
        if self.target_kl is not None:
            check_finite(self, "target_kl", positive=True)
        check_finite(self, "initial_alpha", positive=True)
        if self.target_entropy is not None and not math.isfinite(self.target_entropy):
            raise ConfigError(f"target_entropy must be a finite number, got {self.target_entropy}")
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        for algorithm, names in ALGORITHM_SETTINGS.items():
            if self.algorithm != algorithm and any(getattr(self, name) != defaults[name] for name in names):
                raise ConfigError(f"{', '.join(names[:-1])} and {names[-1]} are {algorithm.upper()} settings; "
                                  f"--algorithm is {self.algorithm}")
        if self.q_bounds is not None and not (len(self.q_bounds) == 2 and all(map(math.isfinite, self.q_bounds))
                                              and self.q_bounds[0] < self.q_bounds[1]):
            raise ConfigError(f"q_bounds must be two finite numbers LO < HI, got {self.q_bounds}")
        if not self.net_arch or min(self.net_arch) < 1:
            raise ConfigError(f"net_arch must list positive layer widths, got {self.net_arch}")
        resolve_device(self.device)


def is_dagger(extra_action_key: str) -> bool:
    """Whether rounds teach the expert's labels on every rollout (DAgger) rather than the successes' own actions."""
    return extra_action_key == EXPERT_ACTION_KEY
