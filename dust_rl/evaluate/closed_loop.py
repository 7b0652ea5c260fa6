"""Closed-loop evaluation of a trained policy (``dust-rl eval``).

Each task runs in its own torchrl ``Collector`` (``num_collectors=workers`` env
processes when ``workers > 1``, each building the policy from the checkpoint
file), which yields one whole episode at a time. Episode ``k`` of every task
resets from seed ``seed + k`` (workers share the seeds through
:class:`~dust_rl.data.seeding.SeedSchedule`), and the policy's sampling noise
is seeded by the episode seed too (:func:`~dust_rl.agents.execution.episode_generator`),
so an episode's outcome depends on its seed only: the same config gives the
same episodes, bit for bit, with any number of workers. Exactly ``episodes``
seeds count per task; episodes the workers start past them are dropped.

Everything that can be wrong with the inputs (counts, missing or corrupt
checkpoint, a policy that does not fit the env, unknown tasks, sampler
settings) is checked in this process before any worker starts. A
``max_steps`` reaches the env's own time limit (:func:`~dust_rl.envs.factory.make_env`),
above the task's default as well as below it. The report (JSON, markdown, success
plot, loss curves of the training run) is written by :mod:`dust_rl.evaluate.report`;
videos of the first episodes of each task by :mod:`dust_rl.evaluate.video`, from
the evaluated trajectories themselves. One evaluation writes into a folder at a time (it holds the folder's
lock, as training and collection do), and never into a training run's or a policy's folder (their
``config.json``, ``loss.png`` and checkpoints are not an evaluation's to overwrite); the videos of an earlier
evaluation in the folder go when its report is replaced, so a folder never shows two policies' episodes.
"""

from __future__ import annotations

import contextlib
import functools
import pathlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector
from torchrl.envs import InitTracker, StepCounter, TransformedEnv
from tqdm import tqdm

from dust_rl.agents import DustPolicy, SamplerConfig, load_policy
from dust_rl.agents.factory import check_fits_env
from dust_rl.agents.model.precision import Precision
from dust_rl.data.seeding import HELDOUT_SEED, EpisodeSeedWrapper, SeedSchedule, check_seeds
from dust_rl.envs.factory import check_tasks, make_env
from dust_rl.envs.torchrl_env import make_torchrl_env
from dust_rl.errors import ConfigError, UserError, check_at_least
from dust_rl.evaluate.records import Episode, wilson_interval
from dust_rl.evaluate.report import plot_loss_curves, write_report
from dust_rl.evaluate.resampling import Resampling, apply_sampling, describe_sampler, resolved_sampler
from dust_rl.evaluate.video import Decoder, decoder_for, write_episode_video
from dust_rl.keys import ACTION_KEY, SEED_KEY, STATE_KEY, STEP_KEY, SUCCESS_KEY
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import episode_collector, torch_threads
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.runtime.workers import Backend, Workers, ray_runtime
from dust_rl.storage.config_json import config_json
from dust_rl.storage.lock import folder_lock

# Torch threads of each evaluation worker unless --runtime.threads says otherwise: a worker's renderer uses the
# other core of a 2-core CPU, and more threads than cores slow torch down many times over.
WORKER_THREADS = 1


def eval_runtime(runtime: RuntimeSettings) -> RuntimeSettings:
    """A training command's runtime as the evaluations it runs use it: on its device, with its progress bars,
    :data:`WORKER_THREADS` threads per worker, at fp32 and uncompiled (a report means the same whatever precision
    trained the policy)."""
    return runtime.at_fp32(threads=WORKER_THREADS)


@dataclass
class EvalConfig:
    """Closed-loop evaluation of a trained policy: success per task with 95% intervals, videos, a report."""

    policy: pathlib.Path
    """Policy file written by training (save_policy), or a fine-tuned RL agent's `rl_agent.pt` (`dust-rl finetune
    steer|residual`: evaluated on its fine-tuning task by default, in 1 local worker)."""
    out: pathlib.Path = pathlib.Path("runs/eval")
    """Folder for report.json, report.md, success.png, loss.png and videos/."""
    env: str | None = None
    """Gymnasium env id; default: the one the policy was trained in (policy.info["env_id"])."""
    tasks: tuple[str, ...] = ()
    """Tasks to evaluate; default: the policy's training tasks (policy.info["tasks"])."""
    episodes: int = 20
    """Episodes per task."""
    workers: int = 2
    """Env processes (or Ray actors) per task; 1 local worker runs in this process."""
    backend: Backend = "local"
    """Where the workers run: processes on this machine, or actors on a Ray cluster (`pip install
    "dust-rl[ray]"`); same episodes either way."""
    ray_address: str | None = None
    """Ray cluster to join with `--backend ray` (e.g. `auto`); default: start a local one for the command."""
    seed: int = HELDOUT_SEED
    """Episode k of a task resets from seed + k (training data uses seeds from 0 on)."""
    sampling: Resampling = None
    """How chunks are sampled: as the policy file says (the default), or `resample` with other settings, given
    after every other argument (`dust-rl eval --policy P resample --n-action-steps 8 --vision-step-ratio 4`; fields
    not given take their defaults, not the file's)."""
    execute_steps: int | None = None
    """Actions executed per chunk before re-planning (1..H); default: the policy's (training's)."""
    max_steps: int | None = None
    """Time limit per episode in env steps; default: the task's."""
    videos: int = 1
    """Episodes per task recorded as MP4 (camera views beside the decoded predicted future)."""
    train_dir: pathlib.Path | None = None
    """Training run folder whose CSV logs give the loss curves; default: the policy file's folder."""
    decoder: pathlib.Path | None = None
    """Token decoder file that draws the predicted future in the videos when the image encoder cannot decode its
    tokens (`dust-rl encoder fit-decoder`); default: `token_decoder.pt` beside the policy file, if there is one."""
    mean_cameras: tuple[str, ...] = ()
    """Cameras whose frozen tokens are replaced by the training data's mean token while acting: an ablation of
    what those views give the policy (`dust-rl diagnose cameras` runs one per camera)."""
    runtime: RuntimeSettings = runtime_field(threads=WORKER_THREADS)
    """Where the policy runs, its threads per worker (`--runtime.threads`), precision, compilation, progress bars;
    the envs run on the CPU."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "episodes", "workers", "max_steps", "execute_steps")
        check_at_least(self, 0, "videos", "seed")
        check_seeds(self.seed, self.episodes + self.workers)  # each worker may start one episode past the last
        self.worker_pool()

    def worker_pool(self) -> Workers:
        """Where and how many workers run episodes."""
        return Workers(self.workers, self.backend, self.runtime.thread_count, self.ray_address)


@dataclass(frozen=True)
class EvalSetup:
    """What every worker needs to rebuild the evaluated env and policy; picklable."""

    policy_path: pathlib.Path
    env_id: str
    env_kwargs: dict
    tasks: tuple[str, ...]
    sampler: SamplerConfig  # resolved: its name is set
    execute_steps: int
    fps: int  # of the env's control loop: the videos' frame rate
    device: str  # where each worker's policy runs (resolved, e.g. "cuda:0")
    precision: Precision = "fp32"
    compile: bool = False
    mean_cameras: tuple[str, ...] = ()


def make_eval_env(env_id: str, env_kwargs: dict, schedule: SeedSchedule, count_steps: bool = False) -> TransformedEnv:
    """A torchrl env (VLA keys) resetting from ``schedule``, with ``episode_seed``, ``is_success`` and ``is_init``;
    ``count_steps``: also ``step_count``, the env steps since the reset (torchrl's ``StepCounter``), for an actor
    that reads it."""
    env = make_torchrl_env(EpisodeSeedWrapper(make_env(env_id, env_kwargs), schedule))
    if count_steps:
        env.append_transform(StepCounter())
    env.append_transform(InitTracker())
    return env


class FiniteActions(TensorDictModuleBase):
    """The evaluated policy (or an actor around it) whose every action is checked to be finite.

    Why: the env refuses a NaN action with a traceback from inside the collector; a policy whose weights load clean
    can still overflow into NaN (statistics near zero), and the error should name the policy file.

    Args:
        actor: the torchrl policy that writes ``action``.
        source: the policy file, named in the error.
    """

    def __init__(self, actor: TensorDictModuleBase, source: pathlib.Path) -> None:
        super().__init__()
        self.actor, self.source = actor, source
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.actor(tensordict)
        if not bool(torch.isfinite(out.get(ACTION_KEY)).all()):
            raise UserError(f"{self.source}: the policy's action holds NaN or infinity (at episode seed "
                            f"{out.get(SEED_KEY).reshape(-1).tolist()}); its weights or statistics overflow: "
                            "retrain it or re-export it from a run that did not diverge")
        return out


def make_eval_policy(setup: EvalSetup) -> FiniteActions:
    """The policy of one worker process, built from the checkpoint file (a live policy is not pickled)."""
    policy = load_policy(setup.policy_path, execute_steps=setup.execute_steps).to(setup.device)
    policy.set_sampler(setup.sampler)
    policy.set_runtime(setup.precision, setup.compile)
    policy.set_mean_cameras(setup.mean_cameras)
    return FiniteActions(policy.executor(seeded=True), setup.policy_path)


def prepare(config: EvalConfig) -> tuple[DustPolicy, EvalSetup]:
    """Load the policy and resolve env, tasks and sampler, raising every input error before workers start.

    Raises:
        CheckpointError: missing or corrupt policy file, or a policy that does not fit the env.
        ConfigError: no env id or tasks to evaluate, unknown task, bad sampler settings.
    """
    policy = load_policy(config.policy, execute_steps=config.execute_steps)  # checks the range
    return policy, eval_setup(config, policy.to(resolve_device(config.runtime.device)))


def eval_setup(config: EvalConfig, policy: DustPolicy) -> EvalSetup:
    """:func:`prepare` of a policy already loaded from ``config.policy`` and on ``config.runtime.device`` (a
    fine-tuning run evaluates the policy it holds): resolve env, tasks and sampler, check them, set the policy's
    sampler and runtime.

    Raises:
        CheckpointError: a policy that does not fit the env.
        ConfigError: no env id or tasks to evaluate, unknown task, bad sampler settings.
    """
    device, runtime = resolve_device(config.runtime.device), config.runtime
    env_id = config.env or policy.info.get("env_id")
    tasks = tuple(config.tasks or policy.info.get("tasks", ()))
    if not env_id or not tasks:
        raise ConfigError(f"{config.policy} does not record its env id and tasks: give --env and --tasks")
    env_kwargs = {k: v for k, v in policy.info.get("env_kwargs", {}).items() if k != "task"}
    if config.max_steps is not None:
        env_kwargs["max_episode_steps"] = config.max_steps
    check_tasks(env_id, env_kwargs, tasks)
    probe = make_eval_env(env_id, {**env_kwargs, "task": tasks[0]}, SeedSchedule(config.seed))
    try:
        check_fits_env(policy, probe, config.policy)
        fps = probe.base_env.metadata["render_fps"]
    finally:
        probe.close()
    apply_sampling(policy, config.sampling, config.policy)
    sampler = resolved_sampler(policy)
    policy.set_runtime(runtime.precision, runtime.compile)
    try:
        policy.set_mean_cameras(config.mean_cameras)
    except ValueError as err:
        raise ConfigError(f"--mean-cameras: {err}") from err
    return EvalSetup(config.policy, env_id, env_kwargs, tasks, sampler, policy.execute_steps, fps, str(device),
                     runtime.precision, runtime.compile, config.mean_cameras)


def eval_collector(setup: EvalSetup, task: str, policy: DustPolicy, workers: Workers, seed: int,
                   actor: TensorDictModuleBase | None = None) -> contextlib.AbstractContextManager[BaseCollector]:
    """A collector yielding one whole episode of ``task`` at a time, seeds from ``seed`` on (a context).

    One local worker runs in this process with ``policy.executor(seeded=True)``, or with ``actor``, a torchrl
    policy built here around ``policy`` (its env counts its steps when it reads ``step_count``); other workers build
    theirs from the checkpoint.

    Raises:
        ValueError: an ``actor`` with workers other than one local one (it lives in this process).
    """
    local = workers.count == 1 and workers.backend == "local"
    if actor is not None and not local:
        raise ValueError(f"an actor built in this process runs in one local worker, not {workers.count} "
                         f"({workers.backend})")
    count_steps = actor is not None and STEP_KEY in actor.in_keys
    env_fns = [functools.partial(make_eval_env, setup.env_id, {**setup.env_kwargs, "task": task},
                                 SeedSchedule(seed, worker=worker, num_workers=workers.count), count_steps)
               for worker in range(workers.count)]
    actor = FiniteActions(policy.executor(seeded=True) if actor is None else actor, setup.policy_path)
    return episode_collector(env_fns, workers, policy=actor,
                             policy_factory=None if local else functools.partial(make_eval_policy, setup),
                             policy_device=setup.device)


def episode_of(trajectory: TensorDictBase) -> Episode:
    """Seed, success, length and digest of one collected trajectory ``[T]``; raises if it is not one whole episode."""
    seeds = trajectory.get(SEED_KEY).reshape(-1)
    done = trajectory.get(("next", "done")).reshape(-1)
    if (seeds != seeds[0]).any() or not done[-1] or done[:-1].any():
        raise RuntimeError(f"collector returned a trajectory that is not one whole episode (seeds {seeds.unique()})")
    success = trajectory.get(("next", SUCCESS_KEY))[-1].any()
    return Episode.of(seeds[0], success, trajectory.get("action"), trajectory.get(("next", *STATE_KEY))[-1])


def run_task(collector: BaseCollector, seeds: range, bar: tqdm,
             keep: int = 0) -> tuple[list[Episode], dict[int, TensorDictBase]]:
    """The episodes of exactly ``seeds``, in seed order, from a collector, and the trajectories of the first
    ``keep`` seeds by seed (for videos)."""
    episodes: dict[int, Episode] = {}
    kept: dict[int, TensorDictBase] = {}
    for trajectory in collector:
        episode = episode_of(trajectory)
        if episode.seed in seeds and episode.seed not in episodes:
            episodes[episode.seed] = episode
            if episode.seed in seeds[:keep]:
                kept[episode.seed] = trajectory
            bar.update(1)
            bar.set_postfix(success=sum(e.success for e in episodes.values()))
            if len(episodes) == len(seeds):
                break
    return [episodes[seed] for seed in seeds], kept


def summary_row(name: str, episodes: Sequence[Episode]) -> dict:
    """Episode count, successes, success rate with its 95% Wilson interval, mean lengths."""
    successes = sum(e.success for e in episodes)
    low, high = wilson_interval(successes, len(episodes))
    success_lengths = [e.length for e in episodes if e.success]
    return {"task": name, "episodes": len(episodes), "successes": successes,
            "success_rate": successes / len(episodes), "ci95_low": low, "ci95_high": high,
            "mean_length": sum(e.length for e in episodes) / len(episodes),
            "mean_length_success": sum(success_lengths) / len(success_lengths) if success_lengths else None}


def task_row(task: str, episodes: Sequence[Episode], videos: list[dict]) -> dict:
    """:func:`summary_row` plus the seeds, each episode (:meth:`Episode.to_json`), and the videos."""
    return {**summary_row(task, episodes), "seeds": [e.seed for e in episodes],
            "per_episode": [e.to_json() for e in episodes], "videos": videos}


def evaluate_task(setup: EvalSetup, task: str, policy: DustPolicy, config: EvalConfig,
                  actor: TensorDictModuleBase | None = None,
                  ) -> tuple[list[Episode], dict[int, TensorDictBase], float, float]:
    """The episodes of ``task``, the trajectories of the first ``config.videos`` of them, the collector's
    start-up seconds and the seconds spent running episodes; ``actor``: see :func:`eval_collector`."""
    start = time.perf_counter()
    with (eval_collector(setup, task, policy, config.worker_pool(), config.seed, actor) as collector,
          tqdm(total=config.episodes, desc=f"eval {task}", disable=not config.runtime.progress) as bar):
        started = time.perf_counter()
        episodes, kept = run_task(collector, range(config.seed, config.seed + config.episodes), bar, config.videos)
    # A multi-process collector's shutdown raises this process's thread count; more threads than
    # cores next to the renderer's own threads slow torch down many times over.
    torch.set_num_threads(config.runtime.thread_count)
    return episodes, kept, started - start, time.perf_counter() - started


def task_videos(task: str, episodes: Sequence[Episode], trajectories: dict[int, TensorDictBase],
                policy: DustPolicy, decoder: Decoder | None, config: EvalConfig, fps: int) -> list[dict]:
    """``<out>/videos/<task>_seed<seed>.mp4`` of the kept evaluated episodes; one ``{"seed", "success", "length",
    "digest", "path", "fps"}`` each."""
    rows = []
    for episode in episodes:
        if episode.seed in trajectories:
            path = config.out / "videos" / f"{task}_seed{episode.seed}.mp4"
            write_episode_video(trajectories[episode.seed], policy, decoder, path, fps)
            rows.append({**episode.to_json(), "path": str(path), "fps": fps})
    return rows


NOISE_SEEDING = "the policy's sampling noise restarts from the episode seed at every reset"


@contextlib.contextmanager
def eval_folder(out: pathlib.Path) -> Iterator[None]:
    """Hold ``out`` for one evaluation: refused when it holds a training run or a policy folder (a ``config.json``,
    which an evaluation never writes: the report's ``loss.png`` and videos would land among its files), locked
    (:func:`~dust_rl.storage.lock.folder_lock`), and cleared of an earlier evaluation's videos, whose report this
    one replaces.

    Raises:
        ConfigError: ``out`` holds a training run or a policy.
        FolderBusyError: another evaluation (or a run) writes into ``out``.
    """
    if (out / "config.json").exists():
        raise ConfigError(f"{out} holds a training run or a policy (config.json), whose files an evaluation would "
                          f"overwrite; give --out a folder of its own, e.g. {out / 'eval'}")
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out):
        for stale in sorted((out / "videos").glob("*.mp4")):
            stale.unlink()
        yield


def evaluate(config: EvalConfig, command: str | None = None, policy: DustPolicy | None = None,
             actor: TensorDictModuleBase | None = None, about: dict | None = None) -> dict:
    """Evaluate a policy in closed loop and write the report, plots and videos to ``config.out``.

    Args:
        config: what to evaluate and how.
        command: the command line that produced this run, quoted in the markdown report.
        policy: the policy, already loaded from ``config.policy``; default: loaded from it, as trained.
        actor: a torchrl actor built around ``policy`` in this process that acts instead of its executor (one local
            worker, :func:`eval_collector`).
        about: report entries on what acts (its ``noise_seeding``), laid over the policy's own.

    Returns:
        The report (also ``config.out / "report.json"``). ``env_steps_per_s`` counts the time spent
        running episodes; the collectors' start-up (worker processes loading the policy) is ``startup_s``.

    Raises:
        CheckpointError: missing or corrupt policy file, or a policy that does not fit the env.
        ConfigError: bad settings (see :func:`prepare`).
    """
    start = time.perf_counter()
    rows, everything, startup, running = [], [], 0.0, 0.0
    with torch_threads(config.runtime.thread_count), ray_runtime(config.worker_pool()):
        policy, setup = prepare(config) if policy is None else (policy, eval_setup(config, policy))
        decoder, decoder_file = decoder_for(policy, config.policy, config.decoder) if config.videos else (None, None)
        with eval_folder(config.out):
            for task in setup.tasks:
                episodes, kept, task_startup, task_running = evaluate_task(setup, task, policy, config, actor)
                videos = task_videos(task, episodes, kept, policy, decoder, config, setup.fps)
                rows.append(task_row(task, episodes, videos))
                everything += episodes
                startup, running = startup + task_startup, running + task_running
            steps = sum(e.length for e in everything)
            loss_plot = plot_loss_curves(config.train_dir or config.policy.parent, config.out / "loss.png")
            report = {
                "policy": str(config.policy), "variant": policy.config.variant,
                "trainable_parameters": sum(p.numel() for p in policy.trainable_modules().parameters()),
                "env_id": setup.env_id,
                "env_kwargs": setup.env_kwargs, "sampler": describe_sampler(setup.sampler), "rl_agent": None,
                "execute_steps": setup.execute_steps, "command": command,
                "config": config_json(config), "seeds": [config.seed, config.seed + config.episodes - 1],
                "noise_seeding": NOISE_SEEDING, "tasks": rows, "overall": summary_row("overall", everything),
                "env_steps": steps, "startup_s": startup, "episodes_time_s": running,
                "env_steps_per_s": steps / running,
                "wall_time_s": time.perf_counter() - start, "loss_plot": str(loss_plot) if loss_plot else None,
                "token_decoder": None if decoder_file is None else str(decoder_file),
            } | (about or {})
            write_report(report, config.out)
    return report


def evaluate_command(config: EvalConfig, command: str | None = None, policy: DustPolicy | None = None,
                     actor: TensorDictModuleBase | None = None, about: dict | None = None) -> dict:
    """``dust-rl eval``: evaluate (:func:`evaluate`), print the success table, say where the report is."""
    report = evaluate(config, command, policy, actor, about)
    for row in [*report["tasks"], report["overall"]]:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful ({100 * row['success_rate']:.0f}%, "
              f"95% CI {100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}%), mean length "
              f"{row['mean_length']:.1f}")
    print(f"report: {config.out / 'report.md'} (also report.json, success.png, loss.png, videos/)")
    return report
