"""Imitation training of DUST (or a baseline) on a demonstration dataset: ``dust-rl train``.

Read top to bottom, CleanRL style: arguments, run folder, policy and cached
features, optimiser / schedule / EMA, resume, the loop, the saved policy.

A run folder holds

* ``config.json``: the full :class:`TrainConfig`, the command and package versions;
* ``checkpoints/checkpoint-<step>/``: torchrl ``Checkpoint`` directories (trainable
  weights, EMA, optimiser, schedule, global RNG state), published atomically with the
  size and SHA-256 of every file (:mod:`dust_rl.storage.checkpoint_dirs`), the last two kept;
  ``--resume`` continues from the newest one once it is checked (a damaged one, or one
  holding anything that could run code when loaded, is refused), and a run killed at any
  point and resumed ends with the same weights as one never interrupted;
* ``logs/``: scalars through torchrl's ``get_logger`` (``--logging.loggers``; by default CSV files
  in ``logs/train/scalars/`` and TensorBoard events in ``logs/train/``, ``train`` being ``--logging.run-name``),
  and in TensorBoard also the config (text and hparams) and each periodic evaluation's success plot and first
  rollout video;
* ``policy.pt``: the EMA policy (:func:`dust_rl.agents.save_policy`), whose ``info``
  names the env, tasks and dataset it was trained for; ``loss.png``.

``--runtime.nproc N`` (or ``torchrun --nproc-per-node N -m dust_rl.train ...``) trains with
``DistributedDataParallel`` over N processes, each on its slice of every global batch
(:mod:`dust_rl.train.distributed`); rank 0 writes the run folder and holds its lock, so a second run into the
same folder is refused, naming the first one's pid.

The frozen backbone's features are cached once per dataset (:class:`~dust_rl.data.features.FeatureCache`).
Every setting is checked when the config is built, and the dataset, env and model before the run
folder is touched; a loss or gradient that stops being finite ends the run before it reaches the
weights, so no checkpoint or ``policy.pt`` holds NaN weights.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import pathlib
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Annotated

import gymnasium as gym
import numpy as np
import torch
import tyro
from PIL import Image
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.checkpoint import Checkpoint, CheckpointRotation
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy, TransformersTextEncoder, load_policy, make_policy, save_policy
from dust_rl.agents.factory import IMAGE_SIZE_INFO, frame_size
from dust_rl.agents.model.flow_matching import Shard
from dust_rl.agents.model.precision import autocast
from dust_rl.data import DatasetError, DemoDataset, DemoWindows
from dust_rl.data.env_state_norm import INFO_KEY as ENV_STATE_NORM_INFO
from dust_rl.data.env_state_norm import PER_TASK, EnvStateNorm
from dust_rl.data.features import FeatureCache, dataset_policy_kwargs, env_state_width, feature_key
from dust_rl.data.video import read_mp4
from dust_rl.diagnose.world_model import vision_skill, windows_of
from dust_rl.envs.factory import make_env
from dust_rl.envs.torchrl_env import make_torchrl_env
from dust_rl.errors import ConfigError, UserError
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.loggers import log_config, log_image, log_scalars, log_video, make_loggers
from dust_rl.runtime.machine import machine_line
from dust_rl.runtime.phase_timer import PhaseTimer
from dust_rl.storage.atomic_files import atomic_write, write_json_atomic
from dust_rl.storage.checkpoint_dirs import run_out_of_space, save_checkpoint_dir
from dust_rl.storage.config_json import config_json
from dust_rl.storage.run_folder import RunRNGState, check_run_folder, locked_run_folder, restore
from dust_rl.train.action_free import ActionFreeBatches, with_action_free
from dust_rl.train.dataset_batches import DatasetBatches
from dust_rl.train.distributed import Ranks, data_parallel, join_process_group, leave_process_group, rank_device, spawn
from dust_rl.train.optim import adamw, averaged_weights, warmup_cosine, weight_average
from dust_rl.train.readout.aux_frame_cache import cached_aux_frames, cached_frame_tokens
from dust_rl.train.readout.aux_frames import FIRST_SEED, HELDOUT_FIRST_SEED, HELDOUT_FRAMES, AuxFrameBatches
from dust_rl.train.readout.cache import readout_cache_path, warm_up_or_load
from dust_rl.train.readout.warmup import warm_up_readout
from dust_rl.train.recipes import LEGACY_RECIPE, RecipeName, recipe_help
from dust_rl.train.settings import DEFAULT_OUT, RETIRED_RUN_SETTINGS, TrainSettings, as_class, grouped_json

# Fields that may differ between a run and its resumption (``recipe`` names where the settings started; they are
# compared one by one).
RESUMABLE_FIELDS = ("resume", "runtime.progress", "runtime.threads", "runtime.device", "runtime.compile",
                    "logging.eval_every", "logging.eval_episodes", "logging.eval_workers", "logging.eval_seed",
                    "logging.keep_best", "logging.loggers", "logging.run_name", "cache_dir", "recipe")
TIMING_FILE = "timing.json"  # where this sitting's time went, phase by phase (dust_rl.runtime.phase_timer)
SKILL_WINDOWS = 256  # training windows the world model's skill is logged on at every periodic evaluation


@dataclass(kw_only=True)
class TrainConfig(TrainSettings):
    """Imitation training of a DUST policy on a demonstration dataset. `--recipe NAME` starts from a measured
    recipe (by default one chosen by the dataset), `--preset cpu-small|gpu-base` from a named policy size; flags
    given beside them override them."""

    dataset: pathlib.Path
    """Dataset folder written by `dust-rl collect` (or `dust-rl dataset import`)."""
    recipe: Annotated[RecipeName, tyro.conf.arg(help=recipe_help(),
                                                help_behavior_hint="(default: chosen by the dataset)")] = LEGACY_RECIPE
    """The named recipe the settings started from (`dust_rl.train.recipes`)."""
    out: pathlib.Path = DEFAULT_OUT
    """Run folder: config, checkpoints, logs, `policy.pt`."""
    resume: bool = False
    """Continue the run in `out` from its newest checkpoint."""
    cache_dir: pathlib.Path | None = None
    """Where the caches derived from the datasets (features, aux frames, read-out fits) go, one subfolder per
    dataset; default: inside each dataset, or the user's cache folder when it is read-only."""

    @classmethod
    def from_settings(cls, settings: TrainSettings, **where) -> TrainConfig:
        """``settings`` with ``dataset``, ``out`` and ``resume`` (``where``) added."""
        return as_class(cls, settings, **where)


class NonFiniteLossError(UserError):
    """Training diverged: the loss or the gradient norm is no longer a finite number."""


@dataclass
class TrainResult:
    """Where a finished run put things, and how it went."""

    policy: pathlib.Path
    out: pathlib.Path
    steps: int
    final_loss: float
    seconds: float
    samples_per_second: float


def train(config: TrainConfig, command: str | None = None) -> TrainResult:
    """Train (or resume training) a policy as described by ``config``; returns where it went.

    With ``nproc`` > 1 it starts that many processes that train data-parallel (unless torchrun started this
    one as one of them).

    Raises:
        DatasetError, CheckpointError, ConfigError: unusable dataset, encoder file or model settings.
        FileExistsError, FileNotFoundError: ``out`` holds a run (without ``resume``), or none (with it).
        FolderLockedError: another run is writing into ``out`` (the message names its pid).
        ConfigError: ``resume`` with settings other than the stored run's.
        NonFiniteLossError: training diverged (the message names the step).
        RankFailedError: with ``nproc`` > 1, a process stopped with one of the errors above.
    """
    if config.runtime.nproc > 1 and "WORLD_SIZE" not in os.environ:  # not started by torchrun: start the processes
        return spawn(config.runtime.nproc, _train_rank, config, command)
    return _train_rank(config, command)


def check_train_folder(config: TrainConfig) -> None:
    """Raise unless ``config.out`` suits ``config.resume`` by training's rule (settings that may change on resume,
    retired ones, earlier names): for a run about to start, and for a finished one reused (``bench suite``)."""
    check_run_folder(config, RESUMABLE_FIELDS, RETIRED_RUN_SETTINGS, grouped_json)


def _train_rank(config: TrainConfig, command: str | None) -> TrainResult:
    """:func:`train` in this process, as one rank of the run when there are several."""
    if config.runtime.threads:
        torch.set_num_threads(config.runtime.threads)
    ranks = _join(config)
    check_train_folder(config)
    ranks.barrier()  # every rank has seen the folder before rank 0 writes it

    # Data, env check, policy (all checked before the run folder is written), cached frozen features.
    dataset = DemoDataset(config.dataset, cache_dir=config.cache_dir)
    env_id, env_kwargs = dataset.meta["env_id"], dataset.meta["env_kwargs"]
    probe = make_env(env_id, {**env_kwargs, "task": dataset.tasks[0]})
    dataset.check_env(probe)
    if config.data.extra_dataset:  # its rows join every batch: the same cameras, frames and sizes
        DemoDataset(config.data.extra_dataset, cache_dir=config.cache_dir).check_env(probe)
    torch.manual_seed(config.seed)
    try:
        policy = _build_policy(config, dataset, probe).to(rank_device(resolve_device(config.runtime.device), ranks))
    finally:
        probe.close()
    with (run_out_of_space(f"training into {config.out}"),
          locked_run_folder(config, RESUMABLE_FIELDS, command, RETIRED_RUN_SETTINGS, grouped_json) if ranks.is_main
          else contextlib.nullcontext()):
        return _train_in_folder(config, ranks, dataset, policy)


def _train_in_folder(config: TrainConfig, ranks: Ranks, dataset: DemoDataset, policy: DustPolicy) -> TrainResult:
    """The run itself, once its folder is this run's (rank 0 holds its lock)."""
    out = config.out
    env_id, env_kwargs = dataset.meta["env_id"], dataset.meta["env_kwargs"]
    # A fine-tuned policy's read-out keeps the object-state units it was trained in (dust_rl.data.env_state_norm).
    state_units = PER_TASK if config.init_policy is None else policy.info.get(ENV_STATE_NORM_INFO)
    policy.info = {"env_id": env_id, "env_kwargs": env_kwargs, "tasks": dataset.tasks,
                   "dataset": str(config.dataset), "variant": policy.config.variant, "steps": config.optim.steps,
                   ENV_STATE_NORM_INFO: state_units, IMAGE_SIZE_INFO: frame_size(dataset.meta["spec"]["image_shape"]),
                   **{name: str(path) if path else None for name, path in (
                       ("video_dataset", config.data.video_dataset), ("extra_dataset", config.data.extra_dataset),
                       ("init_policy", config.init_policy))}}
    timer = PhaseTimer(policy.weights_device)
    with timer("encode dataset"):
        features = _cached_features(config, dataset, policy, ranks)
    start_rows = {"start_rows": config.data.start_rows,
                  "start_fraction": config.data.start_fraction if config.data.start_rows else 0.0}
    n_video, n_extra = (_share(config.optim.batch_size, fraction) if path else 0 for path, fraction in
                        ((config.data.video_dataset, config.data.video_fraction),
                         (config.data.extra_dataset, config.data.extra_fraction)))
    windows = DemoWindows(dataset, horizon=policy.config.horizon, future_offset=policy.config.future_steps,
                          batch_size=config.optim.batch_size - n_video - n_extra,
                          images=False, **start_rows)
    if config.init_policy is None:  # a fine-tuned policy keeps the normalisation its weights were trained with
        policy.normalizer.set_vision_stats(features.image_tokens)
        if policy.config.has_vision:  # every row's frame, as the world model's target sees frames
            policy.normalizer.set_future_stats(
                policy.future_targets(policy.normalizer.normalize_vision(rows.to(policy.weights_device)))
                for rows in features.image_tokens.split(1024))
        if policy.config.has_vision and policy.config.future_target == "change":
            policy.normalizer.set_future_change_scale(_future_change_rms(policy, features, windows))
    # Every periodic evaluation also scores the world model (wm/skill) on one fixed draw of windows.
    skill_features = (features if config.logging.eval_every and policy.config.has_vision and ranks.is_main
                      else None)
    video = _action_free_batches(config, dataset, policy, n_video) if config.data.video_dataset else None
    extra = (DatasetBatches(DemoDataset(config.data.extra_dataset, cache_dir=config.cache_dir), policy, n_extra,
                            config.data.extra_action_key, progress=config.runtime.progress, **start_rows)
             if config.data.extra_dataset else None)
    rotation = CheckpointRotation(out / "checkpoints", keep_last=2)
    loggers = make_loggers(config.logging.loggers, out / "logs", config.logging.run_name) if ranks.is_main else []
    if not config.resume:  # the HParams dashboard sets the loss, and success where it is measured, against them
        log_config(loggers, config_json(config),
                   ["train/loss", *(["eval/success_rate"] if config.logging.eval_every else [])])
    progress = config.runtime.progress and ranks.is_main
    policy.train()
    if config.runtime.compile:
        policy.model.compile()

    # A warmed-up read-out is frozen before the optimiser and EMA see the weights (a resumed run loads it, so
    # its aux frames are not rendered again), as is a fine-tuned policy's; otherwise the aux frames join every
    # step's loss.
    aux, readout_frozen = None, False
    if config.init_policy is not None and policy.readout is not None and policy.readout.reads_frames:
        policy.readout.frame_modules().requires_grad_(False)
        readout_frozen = True
    elif config.readout.warmup_steps:
        if not (config.resume and rotation.latest() is not None):
            _warm_up_readout(config, dataset, policy, timer,
                             (lambda: features.batch(windows.sample())) if config.readout.demos else None,
                             lambda scalars, step: log_scalars(loggers, scalars, step))
        policy.readout.frame_modules().requires_grad_(False)
        readout_frozen = True
    elif config.readout.aux_frames:
        print(_readout_plan(config))
        aux = _aux_frame_batches(config, dataset, policy, timer)

    # Optimiser, schedule, EMA over the trainable modules only (the backbone is frozen).
    trained = policy.trainable_modules()
    optimizer = adamw([p for p in trained.parameters() if p.requires_grad], config.optim.lr,
                      betas=config.optim.betas, weight_decay=config.optim.weight_decay)
    schedule = warmup_cosine(optimizer, config.optim.steps, config.optim.warmup)
    ema = weight_average(trained, config.optim.ema_decay)
    checkpoint = Checkpoint(model=trained, ema=ema, optimizer=optimizer, schedule=schedule, rng=RunRNGState())
    start = _resumed_step(restore(checkpoint, rotation), dataset) if config.resume else 0
    if readout_frozen and policy.config.readout == "tokens":  # its weights final (a resume restored them)
        with timer("read-out estimates"):
            for cache in (features, *(batches.features for batches in (video, extra) if batches is not None)):
                cache.store_readout_estimates()
    loss_of = data_parallel(_ShardLoss(policy, ranks.shard), ranks)

    # The loop.
    bar = tqdm(range(start, config.optim.steps), initial=start, total=config.optim.steps, desc="training",
               disable=not progress)
    tick, samples, losses = time.perf_counter(), 0, None
    began = tick
    for step in bar:
        with timer("step: data"):
            batch = features.batch(windows.sample())[ranks.shard.rows(config.optim.batch_size - n_video - n_extra)]
            if extra is not None:
                batch = torch.cat([batch, extra.sample()])
            if video is not None:
                batch = with_action_free(batch, video.sample())
        with timer("step: forward"), autocast(policy.weights_device, config.runtime.precision):
            losses = loss_of(batch)
            if aux is not None:
                losses.set("loss_aux_frames", policy.readout_loss(aux.sample(config.optim.batch_size)))
                losses.set("loss", losses.get("loss") + policy.config.lambda_aux * losses.get("loss_aux_frames"))
        with timer("step: backward"):
            optimizer.zero_grad(set_to_none=True)
            losses["loss"].backward()
        with timer("step: optimizer"):
            grad_norm = nn.utils.clip_grad_norm_(trained.parameters(), config.optim.grad_clip)
            done = step + 1
            _check_finite(losses["loss"], grad_norm, done, rotation)
            optimizer.step()
            schedule.step()
            ema.update_parameters(trained)
        samples += config.optim.batch_size
        if done % config.logging.log_every == 0 or done == config.optim.steps:
            speed = samples / (time.perf_counter() - tick)
            scalars = {f"train/{k}": ranks.mean(v).item() for k, v in losses.items()}
            scalars |= {"train/lr": schedule.get_last_lr()[0], "train/grad_norm": grad_norm.item(),
                        "train/samples_per_second": speed}
            log_scalars(loggers, scalars, done)
            bar.set_postfix(loss=f"{scalars['train/loss']:.4f}", samples_s=f"{speed:.0f}")
            tick, samples = time.perf_counter(), 0
        if ranks.is_main and (done % config.logging.checkpoint_every == 0 or done == config.optim.steps):
            with timer("checkpoint"):
                save_checkpoint_dir(checkpoint, rotation, done, {"step": done, "dataset": dataset.identity})
        if ranks.is_main and config.logging.eval_every and (done % config.logging.eval_every == 0
                                                            or done == config.optim.steps):
            with timer("periodic eval"), averaged_weights(ema, trained):
                _periodic_eval(config, policy, done, skill_features, loggers)
    bar.close()
    seconds = time.perf_counter() - began
    ranks.check_same(nn.utils.parameters_to_vector(trained.parameters()).detach())
    final = ranks.mean(losses["loss"]).item() if losses is not None else float("nan")
    del loss_of, losses  # DistributedDataParallel's reducer (also held by the losses' graph) goes before its
    gc.collect()         # process group: the other order can hang in the process group's destructor
    ranks.barrier()  # rank 0's last checkpoint is written before any rank returns
    leave_process_group()

    path = out / "policy.pt"
    if ranks.is_main:
        with averaged_weights(ema, trained):
            save_policy(policy, path)
        if config.logging.keep_best:
            _keep_best(out)
        _plot_losses(out)
        write_json_atomic(out / TIMING_FILE, {"machine": machine_line(), "steps": config.optim.steps - start,
                                              "phases": timer.summary()})
    trained_steps = config.optim.steps - start
    return TrainResult(path, out, config.optim.steps, final, seconds,
                       trained_steps * config.optim.batch_size / seconds if seconds and trained_steps else 0.0)


def train_command(config: TrainConfig, command: str | None = None) -> None:
    """``dust-rl train``: train, then say where the policy and logs are."""
    result = train(config, command)
    if int(os.environ.get("RANK", "0")):  # torchrun's other ranks stay quiet
        return
    print(f"trained {result.steps} steps in {result.seconds:.0f} s ({result.samples_per_second:.0f} samples/s); "
          f"final loss {result.final_loss:.4f}")
    print(f"policy: {result.policy}\nlogs: {result.out / 'logs'} ({', '.join(config.logging.loggers)}); "
          f"loss curve: {result.out / 'loss.png'}")
    print(timing_line(json.loads((result.out / TIMING_FILE).read_text())))


def timing_line(timing: dict) -> str:
    """``timing.json`` in one line: each phase's seconds, and milliseconds per step for the step's parts."""
    parts = [f"{phase.removeprefix('step: ')} {row['ms_each']:.0f} ms/step" if phase.startswith("step: ")
             else f"{phase} {row['seconds']:.1f} s" for phase, row in timing["phases"].items()]
    return f"time ({timing['machine']}): " + ", ".join(parts)


def _join(config: TrainConfig) -> Ranks:
    """This process's ranks; under torchrun, ``nproc`` must be 1 or torchrun's process count."""
    ranks = join_process_group(resolve_device(config.runtime.device))
    if config.runtime.nproc not in (1, ranks.world_size):
        raise ConfigError(f"--runtime.nproc {config.runtime.nproc}, but this process is one of {ranks.world_size} "
                          "(torchrun); give one of the two")
    config.check_data_parallel(ranks.world_size)
    return ranks


def _cached_features(config: TrainConfig, dataset: DemoDataset, policy: DustPolicy, ranks: Ranks) -> FeatureCache:
    """The dataset's frozen features: rank 0 encodes and stores them, the other ranks then read the file."""
    if ranks.is_main:
        features = FeatureCache(dataset, policy, progress=config.runtime.progress, store=True,
                                views=config.data.augment_views)
    ranks.barrier()
    if not ranks.is_main:
        features = FeatureCache(dataset, policy, progress=False, store=True, views=config.data.augment_views)
    return features


class _ShardLoss(nn.Module):
    """The policy's loss on one rank's shard of a batch, as a module's forward pass: what
    ``DistributedDataParallel`` wraps (its gradient hooks are armed by its forward)."""

    def __init__(self, policy: DustPolicy, shard: Shard) -> None:
        super().__init__()
        self.policy, self.shard = policy, shard

    def forward(self, batch: TensorDictBase) -> TensorDict:
        return self.policy.compute_loss(batch, shard=self.shard)


def _check_finite(loss: torch.Tensor, grad_norm: torch.Tensor, step: int, checkpoints: CheckpointRotation) -> None:
    """Stop before a non-finite loss or gradient reaches the weights, so no saved state holds NaN."""
    if torch.isfinite(torch.stack([loss.detach(), grad_norm])).all():
        return
    raise diverged(step, f"loss {loss.item()}, gradient norm {grad_norm.item()}", "policy.pt", checkpoints,
                   "lower lr or check the dataset for non-finite values")


def diverged(step: int, what: str, output: str, checkpoints: CheckpointRotation, advice: str) -> NonFiniteLossError:
    """The error of a run that stopped at ``step`` because ``what`` is no longer finite, before ``output`` or a
    checkpoint could hold it (imitation and RL training alike): it names the newest checkpoint, which is intact."""
    latest = checkpoints.latest()
    kept = f"the newest checkpoint, {latest.name}, is intact" if latest else "no checkpoint was written"
    return NonFiniteLossError(f"training diverged at step {step}: {what}; no {output} was written and {kept}; {advice}")


def _resumed_step(metadata: dict, dataset: DemoDataset) -> int:
    """The step a restored checkpoint (its ``metadata``) was saved at, if it was saved on this version of the
    dataset (a checkpoint that predates the record passes).

    Raises:
        DatasetError: the dataset changed since (episodes collected, tasks added, another import).
    """
    saved = metadata.get("dataset")
    if saved is not None and saved != dataset.identity:
        changed = ", ".join(k for k in dataset.identity if saved.get(k) != dataset.identity[k])
        raise DatasetError(f"{dataset.root} changed since this run's checkpoint ({changed}); resume needs the "
                           "dataset it was trained on, or start a new run with another --out")
    return int(metadata.get("step", 0))


def _share(batch_size: int, fraction: float) -> int:
    """Rows of a batch given to a mixed-in dataset: ``fraction`` of it, at least one, and one left for the
    demonstrations."""
    return min(max(1, round(fraction * batch_size)), batch_size - 1)


def _build_policy(config: TrainConfig, dataset: DemoDataset, env: gym.Env) -> DustPolicy:
    """A new policy for ``dataset``, or ``init_policy`` checked against the dataset's env."""
    if config.init_policy is not None:
        return load_policy(config.init_policy, env=make_torchrl_env(env))
    try:
        settings = config.policy
        text_encoder = TransformersTextEncoder(settings.text_encoder) if settings.text_encoder else None
        return make_policy(**settings.model_settings(), image_encoder=settings.image_encoder,
                           text_encoder=text_encoder,
                           execute_steps=settings.execute_steps, future_camera=settings.future_camera,
                           aux_state_dim=env_state_width(dataset) if settings.lambda_aux else 0,
                           **dataset_policy_kwargs(dataset))
    except ValueError as err:  # the model's own config check (e.g. d_model not divisible by n_heads)
        raise ConfigError(f"invalid model settings: {err}") from err


def _warm_up_readout(config: TrainConfig, dataset: DemoDataset, policy: DustPolicy, timer: PhaseTimer,
                     demo_batch: Callable[[], TensorDictBase] | None,
                     log: Callable[[dict[str, float], int], None]) -> None:
    """Fit the read-out alone (:mod:`.readout.warmup`), or load the same fit cached in the dataset folder
    by an earlier run (:mod:`.readout.cache`; not with demonstration batches, ``demo_batch``, whose draws
    depend on more)."""
    path = None if demo_batch is not None else readout_cache_path(dataset.cache_root / "readout_cache", policy, config,
                                                                feature_key(dataset, policy))

    def warm_up(log_fit: Callable[[dict[str, float], int], None]) -> None:
        print(_readout_plan(config))
        heldout = _aux_frame_batches(config, dataset, policy, timer, min(HELDOUT_FRAMES, config.readout.aux_frames),
                                     HELDOUT_FIRST_SEED)
        frames = _aux_frame_batches(config, dataset, policy, timer)
        with timer("read-out fit"):
            warm_up_readout(policy, demo_batch, frames, config.readout.warmup_steps, config.readout.lr, log_fit,
                            config.optim.batch_size, heldout=heldout, progress=config.runtime.progress)

    if warm_up_or_load(path, policy.readout.frame_modules(), config.seed, warm_up, log):
        print(f"read-out warm-up: the fit cached by an earlier run of the same read-out settings ({path})")


def _readout_plan(config: TrainConfig) -> str:
    """One line on the read-out's work before or beside the training steps, printed before its first frame is
    rendered: with a recipe's 8,000 frames that work takes minutes, and without a progress bar nothing else shows."""
    frames = config.readout.aux_frames
    if not config.readout.warmup_steps:
        return (f"read-out: {frames} aux frames (rendered once per dataset), their loss in each of the "
                f"{config.optim.steps} training steps (--readout.aux-frames sets them)")
    return (f"read-out: {frames} aux frames and {min(HELDOUT_FRAMES, frames)} held out (rendered once per dataset), "
            f"{config.readout.warmup_steps} warm-up steps, then the {config.optim.steps} training steps "
            "(--readout.aux-frames and --readout.warmup-steps set them)")


def _aux_frame_batches(config: TrainConfig, dataset: DemoDataset, policy: DustPolicy, timer: PhaseTimer,
                       count: int | None = None, first_seed: int = FIRST_SEED) -> AuxFrameBatches:
    """The run's aux frames (rendered from the dataset's env and tasks, seeded by the run's seed): ``aux_frames``
    of them to fit, or ``count`` from ``first_seed`` on (frames that only measure)."""
    with timer("read-out frames"):
        stored = cached_aux_frames(dataset.cache_root / "aux_frames", dataset.meta["env_id"],
                                   dataset.meta["env_kwargs"], dataset.tasks, policy.cameras,
                                   count or config.readout.aux_frames, env_state_width(dataset),
                                   seed=config.seed, first_seed=first_seed,
                                   close_up_fraction=config.readout.close_up_fraction,
                                   progress=config.runtime.progress)
    with timer("read-out frame tokens"):
        return AuxFrameBatches(stored.rows, stored.instructions, policy, EnvStateNorm.of_dataset(dataset),
                               encode=lambda frames: cached_frame_tokens(stored.path, policy, frames))


def _future_change_rms(policy: DustPolicy, features: FeatureCache, windows: DemoWindows) -> float:
    """Root mean square of the standardised change from each row's frame to its t+H frame, over every window."""
    total, count = 0.0, 0
    with torch.random.fork_rng(devices=[]):  # a feature batch may draw cached views; training's draws stay put
        for window in windows.iterate(1024):
            change = policy.future_changes(features.batch(window)).double()
            total, count = total + change.square().sum().item(), count + change.numel()
    return math.sqrt(total / count) if count else 1.0


def _action_free_batches(config: TrainConfig, dataset: DemoDataset, policy: DustPolicy,
                         batch_size: int) -> ActionFreeBatches:
    """The action-free episodes' batches; with a read-out, only of the demonstrations' tasks, whose object state
    (frozen read-out's loss, logged) means the same.

    Raises:
        DatasetError: a policy with a read-out and action-free episodes of other tasks.
    """
    video = DemoDataset(config.data.video_dataset, cache_dir=config.cache_dir)
    if policy.config.aux_state_dim and set(video.tasks) - set(dataset.tasks):
        raise DatasetError(f"{config.data.video_dataset}: action-free episodes of tasks {sorted(video.tasks)} beside "
                           f"a read-out of {sorted(dataset.tasks)}: their object state means something else; use "
                           "episodes of the demonstrations' tasks, or a policy without --model.lambda-aux")
    return ActionFreeBatches(video, policy, batch_size, progress=config.runtime.progress)



def _periodic_eval(config: TrainConfig, policy: DustPolicy, step: int, skill_features: FeatureCache | None,
                   loggers: list[Logger]) -> None:
    """Log the closed-loop success of ``policy`` (holding the averaged weights), its success plot and the video of
    its first episode (with TensorBoard among the loggers, which shows them), and, given ``skill_features``, the skill
    of its sampled future on a fixed draw of their windows (:mod:`dust_rl.diagnose.world_model`), without touching
    the training RNG. The windows are put in the trunk's units anew each time: their condition tokens come from
    layers that train (windows drawn once at the start read as if the trunk had lost its inputs: a skill of -0.7
    where the policy's own was +0.7)."""
    from dust_rl.evaluate.closed_loop import EvalConfig, eval_runtime, evaluate
    from dust_rl.evaluate.report import SUCCESS_PNG

    folder = config.out / "eval" / f"step-{step:07d}"
    path = save_policy(policy, folder / "policy.pt")
    media = "tensorboard" in config.logging.loggers
    with torch.random.fork_rng():  # evaluate restores this process's torch thread count itself
        report = evaluate(EvalConfig(policy=path, out=folder, episodes=config.logging.eval_episodes,
                                     seed=config.logging.eval_seed, workers=config.logging.eval_workers,
                                     videos=int(media),
                                     runtime=eval_runtime(replace(config.runtime, progress=False))))
    scalars = {f"eval/success_rate/{row['task']}": row["success_rate"] for row in report["tasks"]} | {
        "eval/success_rate": report["overall"]["success_rate"]}
    if skill_features is not None:
        scalars["wm/skill"] = world_model_skill(policy, skill_features, config.seed, config.optim.batch_size)
    log_scalars(loggers, scalars, step)
    if media:
        with Image.open(folder / SUCCESS_PNG) as plot:
            log_image(loggers, "eval/success", np.asarray(plot.convert("RGB")), step)
        task = report["tasks"][0]
        video = task["videos"][0]
        log_video(loggers, f"eval/rollout/{task['task']}", list(read_mp4(pathlib.Path(video["path"]))), video["fps"],
                  step)


def _keep_best(out: pathlib.Path) -> None:
    """``policy.pt`` replaced by the evaluated policy of the highest validation success in ``out/eval/`` (the
    latest of equals: the longest-trained of those that did best), this sitting's and any before a resume."""
    reports = sorted(out.glob(f"eval/step-{'[0-9]' * 7}/report.json"))
    success = {int(path.parent.name.removeprefix("step-")): json.loads(path.read_text())["overall"]["success_rate"]
               for path in reports}
    best = max(success, key=lambda step: (success[step], step))
    with atomic_write(out / "policy.pt", "wb") as file:
        file.write((out / "eval" / f"step-{best:07d}" / "policy.pt").read_bytes())
    curve = ", ".join(f"{step}: {rate:.0%}" for step, rate in sorted(success.items()))
    print(f"policy.pt: the policy of step {best}, the best validation success of the evaluations ({curve})")


def world_model_skill(policy: DustPolicy, features: FeatureCache, seed: int, batch_size: int) -> float:
    """``wm/skill``: the skill of the policy's joint sample against the present frame on the ``SKILL_WINDOWS``
    windows of ``features`` drawn with the run's ``seed``, put in the trunk's units with the weights of now."""
    windows = windows_of(policy, features, SKILL_WINDOWS, seed)
    return vision_skill(policy, windows, buckets=1, seed=seed, batch_size=batch_size)["joint_sample"]["skill"]


def _plot_losses(out: pathlib.Path) -> None:
    from dust_rl.evaluate.report import plot_loss_curves

    plot_loss_curves(out, out / "loss.png")

