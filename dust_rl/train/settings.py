"""What ``dust-rl train`` is told, wherever the data and the run folder are: :class:`TrainSettings`.

Its own module so the named recipes (:mod:`dust_rl.train.recipes`) can build settings that the training loop
(:mod:`dust_rl.train.imitation`) then reads. The settings come in one small group per concern (``--optim.lr``,
``--data.start-rows``, ``--readout.aux-frames``, ``--runtime.device``, ``--logging.eval-every``), each checking
its own values; :class:`TrainSettings` checks the few rules that join groups. Earlier versions kept every setting
at the top level (``--lr``): :data:`GROUPED_SETTINGS` maps those names to the grouped ones, for every reader of
files such versions wrote (run folders, studies, cache keys).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from operator import attrgetter
from typing import Annotated, Literal, TypeVar

import tyro

from dust_rl.agents.config import RETIRED_MODEL_SETTINGS, PolicyConfig
from dust_rl.data.seeding import VALIDATION_SEED
from dust_rl.errors import ConfigError, check_at_least, check_finite, check_fraction
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.loggers import LoggerKind, check_loggers, check_run_name
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.storage.config_json import FLAG_GROUPS, Retired, retired_values

DEFAULT_OUT = pathlib.Path("runs/train")  # dust-rl train's run folder when --out is not given
Config = TypeVar("Config")
# The policy a command builds, as its flags spell it (`--model.*`, FLAG_GROUPS); files keep it under `policy`.
ModelFlags = Annotated[Config, tyro.conf.arg(name=FLAG_GROUPS["policy"])]


@dataclass(kw_only=True)
class OptimSettings:
    """The optimiser and its schedule (`--optim.*`)."""

    steps: int = 3000
    """Optimiser steps."""
    batch_size: int = 64
    """Training windows per step (over all processes: each of `runtime.nproc` takes `batch_size / nproc`)."""
    lr: float = 1e-4
    """Peak learning rate (paper: 1e-4)."""
    betas: tuple[float, float] = (0.95, 0.999)
    """AdamW betas (paper)."""
    weight_decay: float = 1e-5
    """AdamW weight decay (paper)."""
    warmup: float = 0.05
    """Fraction of the steps with a linear learning-rate warm-up; a cosine decay to 0 follows."""
    grad_clip: float = 1.0
    """Gradient-norm clipping threshold."""
    ema_decay: float = 0.999
    """Decay of the exponential moving average of the weights (the saved policy uses the average)."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "steps", "batch_size")
        check_finite(self, "lr", "grad_clip", positive=True)
        check_finite(self, "weight_decay")
        check_fraction(self, "warmup", "ema_decay")
        if len(self.betas) != 2 or not all(0 <= beta < 1 for beta in self.betas):
            raise ConfigError(f"betas must be two numbers in [0, 1), got {self.betas}")


@dataclass(kw_only=True)
class DataSettings:
    """What each batch is drawn from besides the dataset's demonstration windows (`--data.*`)."""

    augment_views: int = 1
    """Cached views per frame: the frame itself plus `augment_views - 1` random shifts with colour jitter
    (`dust_rl.data.augment`); each training window conditions on one of them. Encoding costs that many times
    more, once per dataset."""
    start_rows: int = 0
    """Rows at the start of every episode drawn more often (`dust_rl.data.windows`): the first frame is
    where the policy must decide where to go, and uniform draws give it 1 window in an episode's length;
    0: every row equally likely."""
    start_fraction: float = 0.25
    """Share of each batch drawn from those `start_rows` rows."""
    extra_dataset: pathlib.Path | None = None
    """A second dataset of the same robot and cameras whose windows join every batch with their actions
    (`dust_rl.train.dataset_batches`), e.g. a policy's successful rollouts on fresh layouts (`dust-rl collect
    --policy`)."""
    extra_fraction: float = 0.5
    """Share of each batch taken from `extra_dataset`."""
    extra_action_key: Literal["action", "expert_action"] = "action"
    """The actions `extra_dataset` teaches: the executed ones (self-imitation of a policy's successes) or the
    scripted expert's label at each state (DAgger)."""
    video_dataset: pathlib.Path | None = None
    """A dataset of the same robot and cameras whose episodes train without their actions (action-free video,
    `dust_rl.train.action_free`): the world-model stream learns from them, the action loss does not."""
    video_fraction: float = 0.25
    """Share of each batch taken from `video_dataset`."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "augment_views")
        check_at_least(self, 0, "start_rows")
        for name in ("start_fraction", "video_fraction", "extra_fraction"):
            if not 0 < getattr(self, name) < 1:
                raise ConfigError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        if len(self.mixed_in) == 2 and self.video_fraction + self.extra_fraction >= 1:
            raise ConfigError(f"video_fraction + extra_fraction must be below 1 (the rest are demonstrations), got "
                              f"{self.video_fraction} + {self.extra_fraction}")

    @property
    def mixed_in(self) -> list[str]:
        """The datasets given besides the demonstrations (``video_dataset``, ``extra_dataset``)."""
        return [name for name in ("video_dataset", "extra_dataset") if getattr(self, name) is not None]


@dataclass(kw_only=True)
class ReadoutSettings:
    """How the object-state read-out learns from rendered frames (`--readout.*`)."""

    aux_frames: int = 0
    """Frames of random resets with the arm placed at random (objects independent of the arm,
    `dust_rl.train.readout.aux_frames`) rendered once at the start (and kept in `<dataset>/aux_frames/` for
    any run that asks for the same, `dust_rl.train.readout.aux_frame_cache`); every step adds the read-out's
    error on a batch of them to the loss (weight `lambda_aux`), so the read-out cannot settle for "the target is
    where the gripper is". Needs `lambda_aux` and `readout tokens` or `keypoint_source pixels`; 0: off."""
    close_up_fraction: float = 0.0
    """The share of aux frames with the gripper placed at a step of the task's expert plan (hover, grasp, carry)
    instead of a random walk's end: frames where tasks are decided, for read-outs that can use them (a share of
    close-ups made the read-out of 2026-11 worse, docs/franka_results.md)."""
    warmup_steps: int = 0
    """Steps that fit the read-out (and its pixel keypoints) alone (on aux frames and demonstration rows) before
    the policy trains; they are then frozen (`dust_rl.train.readout.warmup`). Needs `aux_frames`; 0: off."""
    lr: float = 1e-3
    """Learning rate of that warm-up (constant)."""
    demos: bool = True
    """Also fit the warm-up on demonstration rows (half of each batch); without them it sees aux frames only."""

    def __post_init__(self) -> None:
        check_at_least(self, 0, "aux_frames", "warmup_steps")
        check_finite(self, "lr", positive=True)
        check_fraction(self, "close_up_fraction")
        if self.warmup_steps and not self.aux_frames:
            raise ConfigError("--readout.warmup-steps needs --readout.aux-frames > 0: without them the read-out "
                              "learns 'the target is where the gripper is' (dust_rl.train.readout.aux_frames)")


@dataclass(kw_only=True)
class TrainRuntime(RuntimeSettings):
    """Where and how the training runs (`--runtime.*`): every command's runtime settings, and the processes it
    trains over."""

    nproc: int = 1
    """Processes training data-parallel (`DistributedDataParallel`; gloo on the CPU, NCCL with one GPU per
    process on CUDA). Under `torchrun` leave it at 1 or give torchrun's `--nproc-per-node`."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, "nproc")
        cores = os.cpu_count() or 1
        if self.nproc > cores and resolve_device(self.device).type == "cpu":
            raise ConfigError(f"--runtime.nproc {self.nproc} processes on the CPU of a machine with {cores} cores: "
                              f"each would wait on the others; give --runtime.nproc at most {cores}")


@dataclass(kw_only=True)
class LoggingSettings:
    """What the run records while it trains: scalars, checkpoints, periodic evaluations (`--logging.*`)."""

    log_every: int = 50
    """Steps between logged scalars."""
    checkpoint_every: int = 500
    """Steps between checkpoints (one is always written at the end)."""
    eval_every: int = 0
    """Steps between closed-loop evaluations of the EMA policy (0: none); with a vision stream each also logs
    `wm/skill`, the skill of the sampled future against the present frame on a fixed draw of training windows
    (`dust_rl.diagnose.world_model`)."""
    eval_episodes: int = 10
    """Episodes per task of each periodic evaluation."""
    eval_workers: int = 2
    """Env processes of each periodic evaluation."""
    eval_seed: int = VALIDATION_SEED
    """First seed of each periodic evaluation: validation seeds, so a step count chosen on these curves leaves the
    held-out seeds (from 10,000) unseen."""
    keep_best: bool = False
    """Make `policy.pt` the periodic evaluation's policy of the highest validation success (the latest of equals)
    rather than the last step's; needs `eval_every`. Every evaluated policy stays in `out/eval/step-N/`."""
    loggers: tuple[LoggerKind, ...] = ("csv", "tensorboard")
    """Where the scalars go, each through torchrl's `get_logger` into `out/logs/<run_name>`; TensorBoard also gets
    the run's config (text and hparams) and, from each periodic evaluation, its success plot and a rollout video.
    `wandb` and `mlflow` need their package installed. `loss.png` is drawn from the CSV files."""
    run_name: str = "train"
    """The run's name in its loggers: its folder in `out/logs` (the run TensorBoard lists when several runs' logs
    are side by side under one `--logdir`), and wandb's and mlflow's experiment."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "log_every", "checkpoint_every", "eval_episodes", "eval_workers")
        check_at_least(self, 0, "eval_every", "eval_seed")
        check_loggers(self.loggers)
        check_run_name(self.run_name)
        if self.keep_best and not self.eval_every:
            raise ConfigError("--logging.keep-best chooses among periodic evaluations: give --logging.eval-every N")


GROUPS = {"optim": OptimSettings, "data": DataSettings, "readout": ReadoutSettings, "runtime": TrainRuntime,
          "logging": LoggingSettings}
# Each grouped setting under the top-level name earlier versions gave it (what a run folder's config.json, a study's
# results.json or a read-out cache key of theirs holds): its name in the group, but for the read-out's three.
_OLD_NAMES = {"readout.warmup_steps": "readout_warmup", "readout.lr": "readout_lr", "readout.demos": "readout_demos"}
GROUPED_SETTINGS: dict[str, str] = {
    _OLD_NAMES.get(f"{group}.{name}", name): f"{group}.{name}"
    for group, settings in GROUPS.items() for name in settings.__dataclass_fields__}
# Inputs whose batches are drawn apart from the demonstration windows: not split over ranks yet.
NOT_DATA_PARALLEL = ("readout.aux_frames", "readout.warmup_steps", "data.video_dataset", "data.extra_dataset")
# Settings earlier versions had, each at the value every run now has (their other values were measured and did not
# help; docs/franka_results.md), with the commit whose code runs the others: a run stored with one of them at that
# value is still this version's, one stored at another value is not.
RETIRED_RUN_SETTINGS: dict[str, Retired] = {
    **{name: Retired(value, "522ae08") for name, value in (
        ("aux_expert_fraction", 0.0), ("aux_approach_fraction", 0.0), ("aux_approach_displacement", 0.0),
        ("aux_expert_displacement", 0.0), ("readout_lr_decay", False))},
    **{f"policy.{name}": setting for name, setting in RETIRED_MODEL_SETTINGS.items()}}
# Their values alone, as a cached read-out fit's key and a study's recipe hold them (a fit or study stored before a
# setting was retired matches one stored after only at that value).
RETIRED_FIELDS: dict[str, object] = retired_values(RETIRED_RUN_SETTINGS)


def setting(settings: object, name: str) -> object:
    """The value of ``settings``' setting ``name``: a grouped one (``optim.lr``) or its earlier top-level name
    (``lr``, :data:`GROUPED_SETTINGS`)."""
    return attrgetter(GROUPED_SETTINGS.get(name, name))(settings)


def grouped_json(stored: Mapping) -> dict:
    """``stored`` (train settings as JSON values) with the top-level settings of earlier versions moved into their
    groups (:data:`GROUPED_SETTINGS`), so files written before the groups read as this version's."""
    grouped = {k: dict(v) if k in GROUPS and isinstance(v, Mapping) else v for k, v in stored.items()
               if k not in GROUPED_SETTINGS}
    for old, new in GROUPED_SETTINGS.items():
        if old in stored:
            group, _, name = new.partition(".")
            grouped.setdefault(group, {})[name] = stored[old]
    return grouped


@dataclass(kw_only=True)
class TrainSettings:
    """How to train a policy by imitation, wherever the data and the run folder are (`dust-rl quickstart
    --train.*` nests these)."""

    policy: ModelFlags[PolicyConfig] = field(default_factory=PolicyConfig)
    """The policy to build: variant, trunk size, losses, image encoder (`--model.d-model` ...)."""
    optim: OptimSettings = field(default_factory=OptimSettings)
    """The optimiser and its schedule."""
    data: DataSettings = field(default_factory=DataSettings)
    """What each batch is drawn from besides the demonstration windows."""
    readout: ReadoutSettings = field(default_factory=ReadoutSettings)
    """How the object-state read-out learns from rendered frames."""
    runtime: TrainRuntime = field(default_factory=TrainRuntime)
    """Where and how the training runs."""
    logging: LoggingSettings = field(default_factory=LoggingSettings)
    """Scalars, checkpoints, periodic evaluations."""
    init_policy: pathlib.Path | None = None
    """Start from this trained policy (weights, normalisation, read-out) instead of a new one: fine-tuning.
    Its own settings are kept (no `--model.*` flags) and its frame read-out stays frozen (no warm-up)."""
    seed: int = 0
    """Seed of the initial weights, batch sampling and flow-matching noise."""

    def __post_init__(self) -> None:
        readout_on_frames = self.policy.readout == "tokens" or self.policy.keypoint_source == "pixels"
        if self.readout.aux_frames and not (self.policy.lambda_aux and readout_on_frames):
            raise ConfigError("--readout.aux-frames needs --model.lambda-aux > 0 and a read-out frames can train: "
                              "--model.readout tokens, or --model.keypoint-source pixels")
        mixed = self.data.mixed_in
        if self.optim.batch_size < 1 + len(mixed):
            raise ConfigError(f"{' and '.join(mixed)} need --optim.batch-size >= {1 + len(mixed)}: each batch holds "
                              "demonstrations and a share of each")
        if self.init_policy is not None and as_class(PolicyConfig, self.policy) != PolicyConfig():
            raise ConfigError("--model.* flags do not apply with init_policy: fine-tuning keeps the policy's own "
                              "settings (and its read-out, so no aux frames or read-out warm-up either)")
        if self.data.video_dataset is not None and self.policy.lambda_aux and not self.readout.warmup_steps:
            raise ConfigError("--data.video-dataset with --model.lambda-aux needs --readout.warmup-steps: the "
                              "read-out is then fitted first and frozen, so the action-free episodes never train it")
        self.check_data_parallel(self.runtime.nproc)

    def check_data_parallel(self, nproc: int) -> None:
        """Raise unless these settings can train over ``nproc`` processes."""
        if nproc == 1:
            return
        if self.optim.batch_size % nproc:
            raise ConfigError(f"--optim.batch-size {self.optim.batch_size} does not split evenly over {nproc} "
                              "processes")
        used = [name for name in NOT_DATA_PARALLEL if setting(self, name)]
        if used:
            raise ConfigError(f"{', '.join(used)} cannot train over several processes yet; train them with one")


def as_class(cls: type[Config], settings: object, **changes: object) -> Config:
    """``settings`` (a dataclass) with ``changes`` as an instance of ``cls``, a dataclass with the same fields (or
    more, given in ``changes``): the same settings seen through another class's annotations (a nesting command's
    suppressed ones, :class:`NestedTrainSettings`), or with a run's own fields added."""
    return cls(**{**{f.name: getattr(settings, f.name) for f in fields(settings) if f.init}, **changes})


def train_runtime(runtime: RuntimeSettings) -> TrainRuntime:
    """A command's runtime as the runtime of the training it runs, in one process."""
    return as_class(TrainRuntime, runtime)


@dataclass(kw_only=True)
class NestedTrainSettings(TrainSettings):
    """`dust-rl train`'s settings as a command nests them that runs the training itself (`quickstart --train.*`,
    `bench suite --train.*`): where and how it runs is the command's own `--runtime.*`, not set a second time."""

    runtime: tyro.conf.Suppress[TrainRuntime] = field(default_factory=TrainRuntime)

    def under(self, runtime: RuntimeSettings, **changes: object) -> TrainSettings:
        """These settings, with ``changes``, as the training runs them under the command's ``runtime``."""
        return as_class(TrainSettings, self, runtime=train_runtime(runtime), **changes)
