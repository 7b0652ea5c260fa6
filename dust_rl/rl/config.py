"""``dust-rl finetune``'s settings, one config per method, apart from the methods that read them so each method's
module can import them.

``dust-rl finetune METHOD`` (:class:`FinetuneCommand`) takes the settings every method shares
(:class:`FinetuneSettings`) and the method's own: the SB3 methods (``steer``, ``residual``) their RL agent's, with
the algorithm a nested subcommand given last (``sac`` or ``ppo``, each with only the settings it reads);
``self-imitation`` its rounds and how each round trains (the policy's own architecture is kept, so no
``--train.model.*``). Each config records its method (and an SB3 one its algorithm) in the run's ``config.json``;
settings a later version retired (:data:`RETIRED_RL_SETTINGS`) read back at the one value it still honours.
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field
from typing import Annotated, Literal

import tyro

from dust_rl.agents.config import PolicyConfig
from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED, check_seeds
from dust_rl.errors import ConfigError, check_at_least, check_finite
from dust_rl.keys import EXPERT_ACTION_KEY
from dust_rl.runtime.loggers import LoggerKind, check_loggers
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.storage.config_json import Retired, config_from_json, without_retired
from dust_rl.train.settings import DataSettings, NestedTrainSettings, OptimSettings, grouped_json

RL_AGENT_KIND = "dust-rl rl agent"
RL_AGENT_FILE = "rl_agent.pt"  # the fine-tuned policy as one file (dust_rl.rl.fine_tuned_policy)
ROLLOUT_SEED = 20_000  # rollouts start away from the training, validation and held-out seeds
# Steering's largest noise magnitude: the policy samples from N(0, 1) noise in its standardised action units, in
# which the data's actions lie within a few units; a draw past 10 has probability 1.5e-23, so an RL action there
# maps to no chunk the policy was trained to give, and 1e30 overflows the sampler into NaN.
MAX_NOISE_BOUND = 10.0
MAX_RL_SEED = 2**32 - 1  # numpy's legacy seeding, which SB3's set_random_seed calls, takes 32 bits
# rounds: a finished self_imitation run resumed with more rounds goes on from its last round.
RESUMABLE_FIELDS = ("resume", "runtime.progress", "runtime.threads", "runtime.compile", "rounds", "control")
# PPO keeps no replay buffer sized by the run, so a resumed PPO run may also be given a larger budget.
PPO_RESUMABLE_FIELDS = (*RESUMABLE_FIELDS, "steps")


@dataclass
class FinetuneSettings:
    """What every fine-tuning method shares: the policy, the run folder, the task and the held-out comparison."""

    policy: pathlib.Path
    """Policy file written by `dust-rl train`."""
    out: pathlib.Path = pathlib.Path("runs/finetune")
    """Run folder: `config.json`, `report.json`, `report.md` and the method's files."""
    task: str | None = None
    """Task to fine-tune on; default: the policy's first training task."""
    max_steps: int | None = None
    """Time limit per episode in env steps; default: the task's."""
    seed: int = 0
    """Seed of the fine-tuning: the RL agent's and its first training episode's reset, or each self-imitation
    round's training (initial weights aside: the policy's)."""
    eval_episodes: int = 20
    """Closed-loop episodes of the base and the fine-tuned policy, on seeds eval_seed, eval_seed + 1, ..."""
    eval_seed: int = HELDOUT_SEED
    """First evaluation seed (training data: 0 on; validation: 5000 on; held-out: 10000 on)."""
    resume: bool = False
    """Continue the run in `out` where it stopped."""
    runtime: RuntimeSettings = runtime_field(threads=1)
    """Where the policy (and an RL agent) runs, torch threads, the policy's precision, progress bars
    (`--runtime.*`); the envs run on the CPU."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "eval_episodes", "max_steps")
        check_at_least(self, 0, "seed", "eval_seed")
        if self.seed > MAX_RL_SEED:
            raise ConfigError(f"seed must be in [0, {MAX_RL_SEED}] (SB3 seeds numpy's generator, which takes 32 bits), "
                              f"got {self.seed}")
        check_seeds(self.eval_seed, self.eval_episodes + 1, "--eval-seed")  # its one worker may start one more


@dataclass
class CurveSettings(FinetuneSettings):
    """The settings of a method that also draws a learning curve on validation seeds."""

    curve_episodes: int = 10
    """Episodes of each point of the learning curve (`learning_curve.png`)."""
    curve_seed: int = VALIDATION_SEED
    """First seed of the learning curve's evaluations (validation seeds: the held-out ones stay for the report)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, "curve_episodes")
        check_at_least(self, 0, "curve_seed")
        check_seeds(self.curve_seed, self.curve_episodes + 1, "--curve-seed")


@dataclass
class SacSettings:
    """Soft actor-critic (SB3's `SAC`, off-policy, a replay buffer as large as the run)."""

    learning_starts: int = 1000
    """Steps before the first update (uniformly random actions, unless `--initial-std` is set)."""
    updates_per_step: int = 1
    """Gradient steps per RL step of all `--envs` together: U / N per transition with N envs (DSRL: 5 per transition,
    20 with 4 envs; earlier `--gradient-steps`)."""
    target_entropy: float | None = None
    """Learn the entropy coefficient so the policy keeps this entropy (SB3's `ent_coef="auto"`; DSRL: 0),
    starting from `initial_alpha`; with `--initial-std` the std then starts there and is learnt. None: SB3's
    target (minus the action dimension), or with `--initial-std` a fixed std and no entropy bonus
    (`dust_rl.rl.start_at_base`)."""
    initial_alpha: float = 1.0
    """The entropy coefficient's start when it is learnt (SB3's 1.0). Each step's entropy bonus is about alpha
    times the action dimension (112 when steering stack) against a sparse reward of 1, so a steering run with
    `target_entropy` wants it far smaller."""
    name: Literal["sac"] = field(default="sac", init=False)

    def __post_init__(self) -> None:
        check_at_least(self, 0, "learning_starts")
        check_at_least(self, 1, "updates_per_step")
        check_finite(self, "initial_alpha", positive=True)
        if self.target_entropy is not None and not math.isfinite(self.target_entropy):
            raise ConfigError(f"target_entropy must be a finite number, got {self.target_entropy}")


@dataclass
class PpoSettings:
    """Proximal policy optimisation (SB3's `PPO`, on-policy, in rollouts of `n_steps`)."""

    n_steps: int = 2048
    """RL steps per rollout, i.e. between updates (SB3's default; at most `steps`). Steering takes one RL step per
    chunk, so a rollout holds `execute_steps` times as many env steps."""
    n_epochs: int = 10
    """Passes over each rollout (SB3's default)."""
    name: Literal["ppo"] = field(default="ppo", init=False)

    def __post_init__(self) -> None:
        check_at_least(self, 1, "n_steps", "n_epochs")


Algorithm = (Annotated[SacSettings, tyro.conf.subcommand("sac")]
             | Annotated[PpoSettings, tyro.conf.subcommand("ppo")])


@dataclass
class RLSettings(CurveSettings):
    """An SB3 agent trained on top of the frozen policy (`steer`, `residual`); `rl_agent.pt`, `checkpoints/`,
    `logs/` and `learning_curve.json` go to `out`."""

    steps: int = 20_000
    """RL agent steps (chunks when steering, env steps for residual)."""
    reward: Literal["sparse", "dense", "penalty"] = "sparse"
    """The reward while training: the env's (sparse: 1 on success only; dense: that plus potential-based shaping by
    the task's staged progress, shaped for `gamma`: `DustEnv.step`), or penalty: -1 per RL step and 0 on the step
    that succeeds (DSRL's; needs `--finite-horizon`, the time limit then ends an episode as a failure). Evaluation
    counts successes either way."""
    gamma: float = 0.99
    """The RL agent's discount per RL step (an env step for residual, a chunk when steering; steering discounts
    the rewards within a chunk by `gamma ** (1 / execute_steps)` per env step, the discount the dense reward is
    then shaped for)."""
    finite_horizon: bool = False
    """The time limit ends an episode as a failure for the RL agent (terminated: nothing is bootstrapped past it)
    and the agent observes the fraction of the episode left (`dust_rl.rl.frozen_policy_env`). Default: a
    time-limit end is a truncation, bootstrapped as if the episode went on."""
    initial_std: float | None = None
    """Start the RL agent at the base policy (`dust_rl.rl.start_at_base`): mean action 0 (no residual; steering:
    the centre of the base policy's noise) and this exploration standard deviation (SAC: before the tanh), acting so
    from the first step, the std fixed (SAC: no entropy bonus). None: SB3's initialisation (random mean, std ~1 and
    learnt, uniformly random warm-up)."""
    batch_size: int = 256
    """Minibatch size."""
    lr: float = 3e-4
    """Optimiser step size (SB3's default)."""
    net_arch: tuple[int, ...] = (256, 256)
    """Hidden layers of the RL actor and critic."""
    layer_norm: bool = False
    """Normalise each hidden layer of the RL actor and critic before its ReLU (`dust_rl.rl.critic_limits`: caps
    how far the critic's Q extrapolates to actions the actor has not tried; DSRL's setting). PPO's MLPs then use
    ReLU instead of their default tanh."""
    eval_every: int = 0
    """RL steps between evaluations of the agent on `curve_episodes` validation episodes, for the learning curve
    (`learning_curve.json`/`.png`: success against env steps, from the base policy at 0); 0: none."""
    checkpoint_every: int = 5000
    """RL steps between checkpoints of the whole learning state (one is always written at the end; PPO rounds
    each sitting up to whole rollouts of `n_steps`); `--resume` continues from the newest (a PPO run, also with
    a larger `steps`: a finished run goes on to the new budget; SAC's replay buffer is sized by the original
    one)."""
    loggers: tuple[LoggerKind, ...] = ("csv", "tensorboard")
    """Where the agent's scalars go, each through torchrl's `get_logger` into `out/logs` (experiment
    `finetune`), as `dust-rl train`'s do."""
    algorithm: Algorithm = field(default_factory=SacSettings)
    """The stable-baselines3 algorithm (`MultiInputPolicy`) and its own settings, given after every other argument
    (`... ppo --n-steps 512`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, "steps", "batch_size", "checkpoint_every")
        check_at_least(self, 0, "eval_every")
        check_finite(self, "lr", positive=True)
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"gamma must be a discount factor in (0, 1], got {self.gamma}")
        if self.initial_std is not None:
            check_finite(self, "initial_std", positive=True)
        if self.reward == "penalty" and not self.finite_horizon:
            raise ConfigError("--reward penalty pays -1 per step until success: add --finite-horizon, so the time "
                              "limit ends an episode as a failure instead of being bootstrapped past")
        if not self.net_arch or min(self.net_arch) < 1:
            raise ConfigError(f"net_arch must list positive layer widths, got {self.net_arch}")
        check_loggers(self.loggers)


@dataclass
class LatentSettings:
    """The RL action: the policy's initial action noise, or a latent of it (`dust_rl.rl.steering.latent_map`)."""

    latent_dim: int | None = None
    """Size D of the RL action. Da: one row of noise, repeated over the chunk's H rows (pi0's DSRL); another size:
    a fixed random linear map to the H x Da noise (DSRL's robomimic latent is 4 x 7); None: the whole noise,
    H x Da."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "latent_dim")


@dataclass
class SteeringObservation:
    """What the RL agent observes besides the robot state, the pooled image tokens and a read-out's estimate
    (`dust_rl.rl.frozen_policy_env`)."""

    instruction: bool = True
    """The actor and critic also see the pooled instruction: it can name the target (press_button's colour), but
    where a task's instruction is constant it is a constant input (`--no-instruction`)."""
    privileged_critic: bool = False
    """The critic also sees the env's true object state (`observation.environment_state`), the actor never does, so
    the fine-tuned policy acts from images alone (`dust_rl.rl.asymmetric`; SAC)."""


@dataclass
class SteeringCollection:
    """How the transitions are collected (`dust_rl.rl.vector`)."""

    envs: int = 1
    """Envs stepped together, one plan call for all; each RL step then adds `envs` transitions, which `steps`,
    `checkpoint_every`, `eval_every` and PPO's `n_steps` count (multiples of `envs`)."""
    base_warmup: bool = False
    """SAC's `learning_starts` warm-up acts with the base policy's own latents (drawn from N(0, I):
    `dust_rl.rl.steering.prior_latents`) instead of uniformly random ones, so the replay buffer starts with the base
    policy's rollouts (not with `--initial-std`, whose warm-up acts with the actor)."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "envs")


@dataclass
class SteerConfig(RLSettings):
    """Noise steering (DSRL): the RL action is the policy's initial action noise (or a latent of it), one RL step per
    chunk (`dust_rl.rl.steering`)."""

    noise_bound: float = 2.0
    """The noise (or latent) magnitude an RL action of +-1 maps to (DSRL: 1.5)."""
    latent: Annotated[LatentSettings, tyro.conf.OmitArgPrefixes] = field(default_factory=LatentSettings)
    observation: Annotated[SteeringObservation, tyro.conf.OmitArgPrefixes] = field(
        default_factory=SteeringObservation)
    collection: Annotated[SteeringCollection, tyro.conf.OmitArgPrefixes] = field(default_factory=SteeringCollection)
    method: Literal["steer"] = field(default="steer", init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_finite(self, "noise_bound", positive=True)
        if self.noise_bound > MAX_NOISE_BOUND:
            raise ConfigError(f"noise_bound must be at most {MAX_NOISE_BOUND}, got {self.noise_bound}: the policy "
                              "draws its noise from N(0, 1) in standardised action units, never past that")
        envs = self.collection.envs
        counts = {"steps": self.steps, "checkpoint_every": self.checkpoint_every, "eval_every": self.eval_every}
        if isinstance(self.algorithm, PpoSettings):
            counts["n_steps"] = self.algorithm.n_steps
        for name, count in counts.items():
            if count % envs:
                raise ConfigError(f"{name} counts the transitions of all {envs} envs: make it a multiple of --envs, "
                                  f"got {count}")
        sac = isinstance(self.algorithm, SacSettings)
        if self.collection.base_warmup and not (sac and self.initial_std is None):
            raise ConfigError("--base-warmup fills SAC's warm-up steps: it needs sac and no --initial-std (whose "
                              "warm-up acts with the actor)")
        if self.observation.privileged_critic and not sac:
            raise ConfigError("--privileged-critic gives SAC's critic the object state; PPO's is not asymmetric here")


@dataclass
class ResidualConfig(RLSettings):
    """Residual RL: a bounded correction added to every executed action (`dust_rl.rl.residual`)."""

    residual_scale: float = 0.1
    """What an RL action of +-1 adds, as a fraction of the action box's half-width."""
    world_model_obs: bool = False
    """The RL agent (actor and critic) also sees the future DUST sampled jointly with the chunk being executed
    (`dust_rl.rl.residual`); needs a policy that predicts one."""
    method: Literal["residual"] = field(default="residual", init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_finite(self, "residual_scale", positive=True)


@dataclass(kw_only=True)
class RoundData(DataSettings):
    """What each round's batches are drawn from besides the demonstrations; the round's rollouts are its
    `extra_dataset`."""

    extra_dataset: tyro.conf.Suppress[pathlib.Path | None] = None


@dataclass(kw_only=True)
class RoundTraining(NestedTrainSettings):
    """How each self-imitation round fine-tunes (`dust-rl train`'s settings): the policy's architecture is the
    starting policy's, and the starting policy, the rollouts, the seed and the runtime are the round's."""

    policy: tyro.conf.Suppress[PolicyConfig] = field(default_factory=PolicyConfig)
    data: RoundData = field(default_factory=RoundData)
    init_policy: tyro.conf.Suppress[pathlib.Path | None] = None
    seed: tyro.conf.Suppress[int] = 0


RENAMED = {"learning_rate": "lr", "gradient_steps": "updates_per_step"}
"""Earlier names of fine-tuning settings: the RL learning rate (the one name of ``--lr`` across commands), SAC's
update-to-data ratio."""
UNGROUPED_RUNTIME = ("threads", "device", "progress")
"""Runtime settings earlier versions kept beside the others (``--threads``), now in ``runtime``."""

RETIRED_RL_SETTINGS: dict[str, Retired] = {
    f"{group}{name}": Retired(value, "74cb2e1")
    for group in ("algorithm.", "") for name, value in (("q_bounds", None), ("target_kl", None), ("critic_warmup", 0))}
"""SB3 settings earlier versions had, each at the value every run now has: a run folder or ``rl_agent.pt`` stored
with one at that value still resumes and loads, one stored at another value is refused. SAC's ``--q-bounds`` (the
critic squashed into the returns the reward can pay) held Q at its bound on stack and gained nothing
(docs/results/2026-11-26-steering-headroom-on-stack.md); PPO's ``--target-kl`` and ``--critic-warmup`` (the actor
held at the base while the critic fits) slowed a residual's decline on push without stopping it, and steering with
them gained nothing on push or press_button (docs/results/2026-11-27-push-residual-and-steering-ppo.md). Without the
``algorithm.`` group: runs from before the algorithm had its own settings."""


def as_this_version(stored: dict) -> dict:
    """A stored fine-tuning config by this version's names (:data:`RENAMED`, also among an SB3 algorithm's
    settings), its runtime settings grouped (:data:`UNGROUPED_RUNTIME`), a self-imitation round's training settings
    grouped (:func:`~dust_rl.train.settings.grouped_json`)."""
    runtime = {key: stored[key] for key in UNGROUPED_RUNTIME if key in stored}
    stored = {RENAMED.get(key, key): value for key, value in stored.items() if key not in runtime}
    if runtime:
        stored["runtime"] = {**runtime, **stored.get("runtime", {})}
    if isinstance(stored.get("algorithm"), dict):
        stored["algorithm"] = {RENAMED.get(key, key): value for key, value in stored["algorithm"].items()}
    if not isinstance(stored.get("train"), dict):
        return stored
    return {**stored, "train": grouped_json(stored["train"])}


@dataclass
class SelfImitationConfig(CurveSettings):
    """Self-imitation: the policy fine-tuned on its demonstrations and its own successful rollouts, round after round
    (`dust_rl.rl.self_imitation`; each round writes a `policy.pt`, no RL agent)."""

    rounds: int = 1
    """Rounds of rollouts and fine-tuning (`--resume` with more rounds extends a run)."""
    rollout_successes: int = 150
    """Successful rollouts each round collects (its failures are stored only for DAgger,
    `--train.data.extra-action-key expert_action`)."""
    rollout_seed: int = ROLLOUT_SEED
    """First seed of the rollouts; round r starts 10,000 seeds further on per round."""
    demos: pathlib.Path | None = None
    """The demonstrations fine-tuning keeps training on; default: the policy's training dataset
    (`info["dataset"]`)."""
    train: RoundTraining = field(default_factory=lambda: RoundTraining(optim=OptimSettings(steps=3000, lr=1e-4)))
    """How each round fine-tunes (`--train.optim.steps`, `--train.optim.lr`, `--train.data.extra-fraction`,
    `--train.data.start-rows` ...; `--train.data.extra-action-key expert_action`: DAgger)."""
    control: bool = True
    """Also fine-tune the base policy on its demonstrations alone, for as many steps as all rounds together, and
    report it as a row: the gain a method is credited with is the one above that control (on push the
    demonstrations alone gave 68% held-out where a search distillation gave 62%: docs/results)."""
    method: Literal["self_imitation"] = field(default="self_imitation", init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, "rounds", "rollout_successes")
        check_at_least(self, 0, "rollout_seed")


FinetuneConfig = SteerConfig | ResidualConfig | SelfImitationConfig
RLConfig = SteerConfig | ResidualConfig


@dataclass
class FinetuneCommand:
    """Fine-tune a trained DUST policy: steer its noise or add a residual with an SB3 agent (the policy frozen), or
    imitate its own successes."""

    method: (Annotated[SteerConfig, tyro.conf.subcommand("steer")]
             | Annotated[ResidualConfig, tyro.conf.subcommand("residual")]
             | Annotated[SelfImitationConfig, tyro.conf.subcommand("self-imitation")])
    """The fine-tuning method (`dust-rl finetune METHOD --help` lists its settings)."""


METHOD_CONFIGS: dict[str, type] = {config.method: config
                                   for config in (SteerConfig, ResidualConfig, SelfImitationConfig)}
ALGORITHM_CONFIGS: dict[str, type] = {"sac": SacSettings, "ppo": PpoSettings}


def rl_config_from_json(values: dict, device: str | None = None, **changes) -> RLConfig:
    """The config of an SB3 run as its ``config.json`` (or ``rl_agent.pt``) records it, on ``device`` (None: the stored
    one), with ``changes``; fields the
    run predates keep their defaults, earlier names read as today's (:func:`as_this_version`), retired settings at
    the value every run now has are left out (:data:`RETIRED_RL_SETTINGS`), and a run from before the algorithm had
    its own settings (``"algorithm": "sac"``, its settings beside the others) reads too.

    Raises:
        TypeError, KeyError, ValueError, ConfigError: ``values`` is not such a record (not an object of settings, an
            unknown method or algorithm, a setting out of range, a retired setting at another value: the message
            names it and the commit that runs it).
    """
    if not isinstance(values, dict):
        raise TypeError(f"the fine-tuning settings are {values!r:.60}, not an object of settings")
    values = as_this_version(without_retired(values, RETIRED_RL_SETTINGS))
    if device is not None:  # where it runs now, checked on this machine instead of the one it trained on
        values["runtime"] = {**values.get("runtime", {}), "device": device}
    settings = values.get("algorithm", "sac")
    if isinstance(settings, str):
        algorithm, settings = ALGORITHM_CONFIGS[settings], values
    else:
        algorithm = ALGORITHM_CONFIGS[settings["name"]]
    return config_from_json(METHOD_CONFIGS[values["method"]], {k: v for k, v in values.items() if k != "algorithm"},
                            policy=pathlib.Path(values["policy"]), out=pathlib.Path(values["out"]),
                            algorithm=config_from_json(algorithm, settings), **changes)


def is_dagger(extra_action_key: str) -> bool:
    """Whether rounds teach the expert's labels on every rollout (DAgger) rather than the successes' own actions."""
    return extra_action_key == EXPERT_ACTION_KEY
