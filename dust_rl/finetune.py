"""RL fine-tuning of a trained DUST policy with stable-baselines3: ``dust-rl finetune``.

Read top to bottom, CleanRL style: arguments, the frozen policy and its env,
the fine-tuning env (noise steering or residual, :mod:`dust_rl.steering`,
:mod:`dust_rl.residual`), the SB3 agent and its training, then a closed-loop
comparison with the base policy on the same held-out seeds.

The imitation policy's weights never change (except with ``self_imitation``,
which writes new policy files beside it), so the base policy stays one
flag away. The RL agent's weights are saved as a plain state dict
(``rl_agent.pt``, read with ``weights_only=True``) rather than SB3's zip,
whose loader unpickles objects. The base row of the comparison is the base
policy run through the same env with its own noise (steering; the bounded
action space cannot hold every draw) or a zero residual, which reproduces its
evaluated episodes exactly (tested).

Every ``checkpoint_every`` RL steps the whole learning state (networks,
optimisers, replay buffer, counters, RNG; :mod:`dust_rl.rl_checkpoint`) goes
to a torchrl ``Checkpoint``; ``--resume`` continues from the newest one.

``--method wm_select`` trains no RL agent: it fits a scorer of DUST's predicted futures on the policy's own
rollouts and writes a policy that picks among K joint samples (:mod:`dust_rl.wm_select`).
``--method self_imitation`` trains no RL agent either: it fine-tunes the policy's own weights on its
successful rollouts (:mod:`dust_rl.self_imitation`). torchrl's SAC front-end is :mod:`dust_rl.torchrl_sac`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.logger import configure as configure_logger
from torchrl.checkpoint import Checkpoint, CheckpointRotation, GlobalRNGState
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy, load_policy, unwrap
from dust_rl.agents.checkpoint_io import save_checkpoint
from dust_rl.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.checkpoint_dirs import save_checkpoint_dir
from dust_rl.config_json import config_json
from dust_rl.critic_limits import LayerNormReLU, bound_critic
from dust_rl.critic_warmup import CriticWarmup
from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED
from dust_rl.device import resolve_device
from dust_rl.env_factory import check_tasks, make_env
from dust_rl.episode_collector import torch_threads
from dust_rl.errors import ConfigError, check_at_least, check_finite
from dust_rl.evaluate import BASE_ROW, Episode, episode_digest, paired_comparison, summary_row
from dust_rl.frozen_policy_env import FrozenPolicyEnv
from dust_rl.report import plot_learning_curve
from dust_rl.residual import ResidualEnv
from dust_rl.rl_checkpoint import SB3LearningState
from dust_rl.run_folder import check_run_folder, locked_run_folder, restore
from dust_rl.search_settings import SearchSettings
from dust_rl.self_imitation import is_dagger, self_imitation
from dust_rl.start_at_base import WarmStartSAC, start_at_base
from dust_rl.steering import NoiseSteeringEnv
from dust_rl.train import TrainSettings
from dust_rl.wm_select import VALIDATION_EVERY, wm_select

RL_AGENT_KIND = "dust-rl rl agent"
# rounds: a finished self_imitation run resumed with more rounds goes on from its last round.
RESUMABLE_FIELDS = ("resume", "progress", "threads", "rounds", "control")
# PPO keeps no replay buffer sized by the run, so a resumed PPO run may also be given a larger budget.
PPO_RESUMABLE_FIELDS = (*RESUMABLE_FIELDS, "steps")
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"sac": SAC, "ppo": PPO}
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
    (:mod:`dust_rl.wm_select`; writes ``policy.pt``, no SB3 agent); ``self_imitation``: the policy fine-tuned on
    its demonstrations and its own successful rollouts, round after round (:mod:`dust_rl.self_imitation`; each
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
    and the agent observes the fraction of the episode left (:mod:`dust_rl.frozen_policy_env`). Default: a
    time-limit end is a truncation, bootstrapped as if the episode went on."""
    noise_bound: float = 2.0
    """Steering: the noise magnitude an RL action of +-1 maps to."""
    residual_scale: float = 0.1
    """Residual: what an RL action of +-1 adds, as a fraction of the action box's half-width."""
    world_model_obs: bool = False
    """Residual: the RL agent (actor and critic) also sees the future DUST sampled jointly with the chunk being
    executed (:mod:`dust_rl.residual`); needs a policy that predicts one."""
    learning_starts: int = 1000
    """SAC: steps before the first update (uniformly random actions, unless ``initial_std`` is set)."""
    gradient_steps: int = 1
    """SAC: gradient steps per RL step, the update-to-data ratio (DSRL: 20)."""
    target_entropy: float | None = None
    """SAC: learn the entropy coefficient so the policy keeps this entropy (SB3's ``ent_coef="auto"``; DSRL: 0),
    starting from ``initial_alpha``; with ``initial_std`` the std then starts there and is learnt. None: SB3's
    target (minus the action dimension), or with ``initial_std`` a fixed std and no entropy bonus
    (:mod:`dust_rl.start_at_base`)."""
    initial_alpha: float = 1.0
    """SAC: the entropy coefficient's start when it is learnt (SB3's 1.0). Each step's entropy bonus is about alpha
    times the action dimension (112 when steering stack) against a sparse reward of 1, so a steering run with
    ``target_entropy`` wants it far smaller."""
    initial_std: float | None = None
    """Start the RL agent at the base policy (:mod:`dust_rl.start_at_base`): mean action 0 (no residual; steering:
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
    """Normalise each hidden layer of the RL actor and critic before its ReLU (:mod:`dust_rl.critic_limits`: caps
    how far the critic's Q extrapolates to actions the actor has not tried; DSRL's setting). PPO's MLPs then use
    ReLU instead of their default tanh."""
    q_bounds: tuple[float, float] | None = None
    """SAC: squash the critic's output into (LO, HI), the returns the reward can pay (sparse: 0 1;
    :mod:`dust_rl.critic_limits`). None: unbounded."""
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
    demonstrations alone gave 68% held-out where the search distillation gave 62%: BENCHMARKS.md, "Search")."""
    search: SearchSettings = field(default_factory=SearchSettings)
    """self_imitation: roll out with a simulator search over the policy's chunks (``--search.candidates K``,
    ``--search.lookahead``, ``--search.noise-scale``; :mod:`dust_rl.search_expert`) and distil its successes:
    expert iteration. One candidate (the default): the policy's own rollouts."""
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
    """Where the frozen DUST policy and the SB3 agent run (:mod:`dust_rl.device`): auto, cpu, cuda, cuda:N, mps;
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
        if self.search.active and (self.method != "self_imitation" or is_dagger(self.train.extra_action_key)):
            raise ConfigError("--search.candidates applies to --method self_imitation, whose rollouts it chooses "
                              "(not with DAgger's expert labels)")
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


def finetune(config: FinetuneConfig, command: str | None = None) -> dict:
    """Fine-tune, save the result, compare with the base policy; returns the report."""
    resumable = PPO_RESUMABLE_FIELDS if config.algorithm == "ppo" else RESUMABLE_FIELDS
    with torch_threads(config.threads):
        check_run_folder(config, resumable)
        policy = unwrap(load_policy(config.policy))
        env_id, env_kwargs, task = policy_env(config, policy)
        demos = config.demos or pathlib.Path(policy.info.get("dataset") or "")
        if config.method == "self_imitation" and not (demos / "meta.json").is_file():
            raise ConfigError(f"self_imitation trains on the policy's demonstrations too; {demos} is not a dataset: "
                              "pass --demos")
        with locked_run_folder(config, resumable, command):
            return _finetune_in_folder(config, command, policy, env_id, env_kwargs, task, demos)


def _finetune_in_folder(config: FinetuneConfig, command: str | None, policy: DustPolicy, env_id: str,
                        env_kwargs: dict, task: str, demos: pathlib.Path) -> dict:
    """The fine-tuning and its report, once the run folder is this run's."""
    if config.method in ("wm_select", "self_imitation"):
        result = (wm_select(config, task, policy) if config.method == "wm_select"
                  else self_imitation(dataclasses.replace(config, demos=demos), task, env_id, env_kwargs))
        episodes = {name: [Episode(*e) for e in row["per_episode"]] for name, row in result["rows"].items()}
        extra = {k: v for k, v in result.items() if k not in ("rows", "train_seconds")}
        trained_s = result["train_seconds"]
    else:
        policy.to(resolve_device(config.device))
        episodes, trained_s = train_rl(config, finetune_env_factory(config, policy)[0])
        extra = {"rl_agent": str(config.out / "rl_agent.pt")}
    report = {
        "policy": str(config.policy), "method": config.method, "algorithm": config.algorithm, "task": task,
        "steps": config.steps, "command": command, "config": config_json(config),
        "seeds": [config.eval_seed, config.eval_seed + config.eval_episodes - 1], "train_seconds": trained_s,
        "rows": [summary_row(name, rows) | ({} if name == BASE_ROW else
                                              {"vs_base": paired_comparison(episodes[BASE_ROW], rows)})
                 for name, rows in episodes.items()],
        "per_episode": {name: [list(e) for e in rows] for name, rows in episodes.items()}, **extra,
    }
    write_json_atomic(config.out / "report.json", report, indent=2)
    write_text_atomic(config.out / "report.md", _markdown(report))
    return report


def train_rl(config: FinetuneConfig, make: Callable[[], FrozenPolicyEnv]) -> tuple[dict[str, list[Episode]], float]:
    """Train the SB3 agent on the fine-tuning env (resuming from the newest checkpoint), save it, and run the
    base and the fine-tuned policy on the evaluation seeds; returns their episodes by row name and the
    training seconds."""
    began = time.perf_counter()
    env = make()
    agent = build_agent(config, env)
    agent.set_logger(configure_logger(str(config.out / "logs"), ["csv", "tensorboard"]))
    checkpoint = Checkpoint(agent=SB3LearningState(agent), rng=GlobalRNGState())
    rotation = CheckpointRotation(config.out / "checkpoints", keep_last=2)
    restored = restore(checkpoint, rotation)
    env.env_steps = int(restored.get("env_steps", 0))
    seconds_before = float(restored.get("train_seconds", 0.0))  # earlier processes' share of a resumed run

    def trained_seconds() -> float:
        return seconds_before + time.perf_counter() - began

    curve_path = config.out / "learning_curve.json"
    curve = [p for p in _read_curve(curve_path) if p["rl_steps"] <= agent.num_timesteps]  # none past the checkpoint
    curve_seeds = range(config.curve_seed, config.curve_seed + config.curve_episodes)
    if config.eval_every and not curve:  # the curve starts at the base policy (the RL agent's "off" action)
        curve.append({"rl_steps": 0, "env_steps": 0,
                      **summary_row(BASE_ROW, _run_episodes(make, lambda obs, env: env.step_base(),
                                                                 curve_seeds, config.progress))})
    sitting = min(config.checkpoint_every, config.eval_every or config.checkpoint_every)
    warmup = CriticWarmup(config.critic_warmup) if config.critic_warmup else None
    while agent.num_timesteps < config.steps:  # in sittings of checkpoint_every (or eval_every) steps
        agent.learn(total_timesteps=min(sitting, config.steps - agent.num_timesteps), reset_num_timesteps=False,
                    progress_bar=config.progress, callback=warmup)
        last_eval = curve[-1]["rl_steps"] if curve else 0
        if config.eval_every and (agent.num_timesteps >= last_eval + config.eval_every
                                  or agent.num_timesteps >= config.steps):
            episodes = _run_episodes(make, _tuned_step(agent), curve_seeds, config.progress)
            curve.append({"rl_steps": agent.num_timesteps, "env_steps": env.env_steps,
                          **summary_row("fine-tuned", episodes)})
            agent.logger.record("eval/curve_success_rate", curve[-1]["success_rate"])
            write_json_atomic(curve_path, curve, indent=2)
            title = f"{config.method} + {config.algorithm}, seeds {curve_seeds.start}..{curve_seeds.stop - 1}"
            plot_learning_curve(curve, config.out / "learning_curve.png", title)
        save_checkpoint_dir(checkpoint, rotation, agent.num_timesteps,
                            {"step": agent.num_timesteps, "env_steps": env.env_steps,
                             "train_seconds": trained_seconds()})
    env.close()
    trained_s = trained_seconds()
    save_checkpoint({"config": config_json(config), "state_dict": agent.policy.state_dict()},
                    config.out / "rl_agent.pt", RL_AGENT_KIND)

    # The base policy and the fine-tuned one on the same held-out seeds; when steering, also the base policy with
    # the centre of its noise (the RL action 0), which a deterministic steering agent starts from.
    seeds = range(config.eval_seed, config.eval_seed + config.eval_episodes)
    step_functions = {"base": lambda obs, env: env.step_base()}
    if config.method == "steer":
        centre = np.zeros(env.action_space.shape, np.float32)
        step_functions["centre"] = lambda obs, env: env.step(centre)
    step_functions["fine_tuned"] = _tuned_step(agent)
    names = {"base": BASE_ROW, "centre": f"{BASE_ROW}, noise at its centre",
             "fine_tuned": f"fine-tuned ({config.method}, {config.algorithm})"}
    rows = {}
    for key, step in step_functions.items():
        rows[names[key]] = episodes = _run_episodes(make, step, seeds, config.progress)
        agent.logger.record(f"eval/success_rate_{key}", summary_row(key, episodes)["success_rate"])
    agent.logger.dump(agent.num_timesteps)
    return rows, trained_s


def build_agent(config: FinetuneConfig, env: FrozenPolicyEnv) -> BaseAlgorithm:
    """The SB3 agent ``config`` asks for, on ``env`` (the same settings rebuild it to resume)."""
    algorithm = ALGORITHMS[config.algorithm]
    kwargs: dict = {"gamma": config.gamma, "learning_rate": config.learning_rate}
    if algorithm is SAC:  # a replay buffer no larger than the run
        kwargs |= {"learning_starts": config.learning_starts, "batch_size": config.batch_size,
                   "buffer_size": config.steps, "gradient_steps": config.gradient_steps}
        if config.initial_std is not None and config.target_entropy is None:
            kwargs["ent_coef"] = 0.0  # the std is fixed: an entropy bonus would only swamp the reward (start_at_base)
        else:
            kwargs["ent_coef"] = f"auto_{config.initial_alpha}"
            if config.target_entropy is not None:
                kwargs["target_entropy"] = config.target_entropy
    else:  # a rollout no longer than the run, minibatches no larger than a rollout
        n_steps = min(config.n_steps, config.steps)
        kwargs |= {"n_steps": n_steps, "batch_size": min(config.batch_size, n_steps), "n_epochs": config.n_epochs,
                   "target_kl": config.target_kl}
    if algorithm is SAC and config.initial_std is not None:
        algorithm = WarmStartSAC
    policy_kwargs = {"net_arch": list(config.net_arch)}
    if config.layer_norm:
        policy_kwargs["activation_fn"] = LayerNormReLU
    agent = algorithm("MultiInputPolicy", env, seed=config.seed, device=resolve_device(config.device),
                      policy_kwargs=policy_kwargs, **kwargs)
    if config.initial_std is not None:
        start_at_base(agent, config.initial_std, learn_std=config.target_entropy is not None)
    if config.q_bounds is not None:
        bound_critic(agent, *config.q_bounds)
    return agent


def finetune_command(config: FinetuneConfig, command: str | None = None) -> dict:
    """``dust-rl finetune``: fine-tune, print the comparison, say where the files are."""
    report = finetune(config, command)
    for row in report["rows"]:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful ({100 * row['success_rate']:.0f}%, "
              f"95% CI {100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}%)")
    print(f"{'policy' if 'policy_file' in report else 'RL agent'}: "
          f"{report.get('policy_file', report.get('rl_agent'))}\nreport: {config.out / 'report.md'}")
    return report


def policy_env(config: FinetuneConfig, policy: DustPolicy) -> tuple[str, dict, str]:
    """The env id, env kwargs (the policy's, with ``max_steps``) and task to fine-tune on, checked."""
    env_id = policy.info.get("env_id")
    if env_id is None:
        raise ConfigError(f"{config.policy}: the policy does not name the env it was trained in (info['env_id'])")
    task = config.task or (policy.info.get("tasks") or [None])[0]
    if task is None:
        raise ConfigError(f"{config.policy}: no training task recorded; pass --task")
    env_kwargs = {k: v for k, v in policy.info.get("env_kwargs", {}).items() if k != "task"}
    if config.max_steps:
        env_kwargs["max_episode_steps"] = config.max_steps
    check_tasks(env_id, env_kwargs, [task])
    return env_id, env_kwargs, task


def finetune_env_factory(config: FinetuneConfig, policy: DustPolicy) -> tuple[Callable[[], FrozenPolicyEnv], str]:
    """A factory of fresh fine-tuning envs for ``config``'s task (checked once, here), and the task."""
    env_id, env_kwargs, task = policy_env(config, policy)
    step_discount = config.gamma ** (1 / policy.execute_steps) if config.method == "steer" else config.gamma

    def make() -> FrozenPolicyEnv:
        env = make_env(env_id, {**env_kwargs, "task": task, "reward_type": config.reward,
                                "shaping_discount": step_discount})
        if config.method == "steer":
            return NoiseSteeringEnv(env, policy, noise_bound=config.noise_bound, step_discount=step_discount,
                                    finite_horizon=config.finite_horizon)
        half_width = (env.action_space.high - env.action_space.low) / 2
        return ResidualEnv(env, policy, residual_scale=config.residual_scale * half_width,
                           world_model=config.world_model_obs, finite_horizon=config.finite_horizon)

    return make, task


def _tuned_step(agent: BaseAlgorithm) -> Callable[[dict, FrozenPolicyEnv], tuple]:
    """An env step with the RL agent's deterministic action."""
    return lambda obs, env: env.step(agent.predict(obs, deterministic=True)[0])


def _read_curve(path: pathlib.Path) -> list[dict]:
    """The learning curve written so far (a resumed run continues it); empty for a new run."""
    return json.loads(path.read_text()) if path.is_file() else []


def _run_episodes(make: Callable[[], FrozenPolicyEnv], step: Callable[[dict, FrozenPolicyEnv], tuple],
                  seeds: range, progress: bool) -> list[Episode]:
    """Closed-loop episodes on ``seeds``; success is the env's ``is_success`` at the end, length and digest count
    env steps, as :func:`dust_rl.evaluate.evaluate` does (equal digests: the same episode)."""
    env, episodes = make(), []
    for seed in tqdm(seeds, desc="episodes", disable=not progress):
        obs, _ = env.reset(seed=seed)
        done, info = False, {}
        while not done:
            obs, _, terminated, truncated, info = step(obs, env)
            done = terminated or truncated
        actions = torch.from_numpy(np.stack(env.executed))
        digest = episode_digest(actions, torch.from_numpy(obs["robot_state"]))
        episodes.append(Episode(seed, bool(info.get("is_success", False)), len(env.executed), digest))
    env.close()
    return episodes


def _versus_base(row: dict) -> str:
    paired = row.get("vs_base")
    return "" if paired is None else f"+{paired['gained']} / -{paired['lost']} (p = {paired['p_value']:.2f})"


def _markdown(report: dict) -> str:
    if report["method"] == "wm_select":
        scorer = report["scorer"]
        auc = "n/a" if scorer["validation_auc"] is None else f"{scorer['validation_auc']:.2f}"
        how = (f"a future scorer fitted on {report['config']['rollouts']} base-policy rollouts "
               f"({report['rollout_env_steps']} env steps, {report['train_seconds']:.0f} s; validation ROC AUC {auc})")
    elif report["method"] == "self_imitation":
        config = report["config"]
        taught = ("and the failures between them, taught the expert" if is_dagger(config["train"]["extra_action_key"])
                  else "taught their actions")
        search = config.get("search", {})
        if SearchSettings(**search).active:
            taught += (f", each rollout a search over {search['candidates']} of the policy's chunks per plan "
                       f"({search['lookahead']} chunks of lookahead, noise x{search['noise_scale']:g})")
        how = (f"{config['rounds']} round(s) of {config['rollout_successes']} successful rollouts {taught} "
               f"({', '.join(str(r['rollouts']) for r in report['rounds'])} episodes; {report['rollout_env_steps']} "
               f"env steps), each followed by {config['train']['steps']} fine-tuning steps "
               f"({report['train_seconds']:.0f} s in all)"
               + ("; the control: as many steps on the demonstrations alone" if config.get("control") else ""))
    else:
        how = (f"{report['algorithm']}, {report['steps']} RL steps ({report['train_seconds']:.0f} s), "
               f"{report['config']['reward']} reward")
    lines = [f"# RL fine-tuning: {report['policy']}", "",
             f"- task `{report['task']}`, method `{report['method']}`: {how}",
             f"- seeds {report['seeds'][0]}..{report['seeds'][1]}; the imitation policy "
             f"{'is fine-tuned' if report['method'] == 'self_imitation' else 'stays frozen'}", "",
             "| policy | episodes | success | 95% CI | episodes won / lost against the base (McNemar p) |",
             "|---|---|---|---|---|"]
    lines += [f"| {row['task']} | {row['episodes']} | {100 * row['success_rate']:.0f}% | "
              f"{100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}% | {_versus_base(row)} |"
              for row in report["rows"]]
    lines += ["", "Reproduce:", "", f"    {report['command']}", ""]
    return "\n".join(lines)
