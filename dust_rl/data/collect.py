"""Collect scripted-expert demonstrations (or a trained policy's rollouts) with torchrl collectors into a
dataset folder.

One torchrl collector per task (:mod:`dust_rl.runtime.episode_collector`: ``workers``
env processes, or Ray actors) runs the expert policy and yields whole
trajectories; each is written as soon as it finishes. Re-running the same call
resumes: seeds with a record are not run again, and the dataset is the first
``episodes`` successful seeds of each task whatever the interruptions, the
number of workers or where they run.

With ``policy`` a trained policy file runs instead of the expert, exactly as
``dust-rl eval`` runs it: a dataset of its successful rollouts on fresh layouts
(self-imitation), or of all of them with the expert's label beside each action
(``keep_failed``; DAgger). The file's digest is part of the dataset's config, so
a resumed collection cannot mix two policies.

Every argument is checked before anything is written; one collection at a time
writes into a folder (:func:`~dust_rl.storage.lock.folder_lock`); and a smaller
``episodes`` than the dataset already holds keeps them all (nothing is deleted
to honour it).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import pathlib
from collections.abc import Sequence

from torchrl.collectors import BaseCollector
from tqdm import tqdm

from dust_rl.agents import load_policy
from dust_rl.envs.factory import check_tasks, make_env
from dust_rl.envs.torchrl_env import make_torchrl_env
from dust_rl.errors import ConfigError, UserError, no_space_left
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import episode_collector, torch_threads
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.runtime.workers import Workers, ray_runtime
from dust_rl.storage.lock import folder_lock

from .collection_env import collection_env_fns
from .episodes import EpisodeRecord, scan_episodes, trajectory_to_episode, write_episode
from .finalize import finalize_dataset
from .layout import clear_staging
from .metadata import open_meta, recorded_env_spec
from .policy import load_rollout_policy, make_expert_policy
from .seeding import check_seeds
from .selection import select_episodes

# Give up on a task when this many seeds per requested episode have not produced enough successes: the
# expert fails rarely; a trained policy worth rolling out succeeds in 5% of its episodes or more.
MAX_SEEDS_PER_EPISODE = {"expert": 3, "policy": 20}
CPU_RUNTIME = RuntimeSettings(device="cpu")  # where a rolled-out policy runs unless told


def seeds_tried(policy: object | None, episodes: int) -> int:
    """The most episodes a task's collection runs for ``episodes`` successes before it gives up, of the scripted
    expert (``policy`` None) or of a policy."""
    return MAX_SEEDS_PER_EPISODE["expert" if policy is None else "policy"] * episodes + 10


class SuccessesOutOfReachError(UserError):
    """The expert or policy succeeds too rarely for the successes asked for: collection gives up."""


def collect_demos(root: str | pathlib.Path, env_id: str = "DustFranka-v0", tasks: Sequence[str] = ("pick_place",),
                  episodes: int = 100, *, env_kwargs: dict | None = None, workers: int | Workers = 1,
                  start_seed: int = 0, noise_std: float = 0.0, keep_failed: bool = False,
                  policy: str | pathlib.Path | None = None, policy_runtime: RuntimeSettings | None = None,
                  progress: bool = True, wait_for_writer: bool = False) -> dict:
    """Collect (or resume collecting) ``episodes`` successful expert demos (or policy rollouts) per task into
    ``root``.

    Args:
        root: dataset folder (created if missing; an existing one must hold the same config).
        env_id: gymnasium id; ``env_kwargs`` (image size, cameras...) go to the env constructor with ``task``.
        tasks: task names; their episodes share one dataset, each with its own instructions.
        episodes: successful episodes per task.
        workers: env processes per collector (1 runs in this process), or where and how many workers run (and a
            policy's torch threads in each).
        start_seed: first seed of every task; episode ``k`` of a task uses seed ``start_seed + k``.
        noise_std: DART perturbation of the executed action (the stored label stays the expert's).
        keep_failed: also store failed episodes (flagged ``success=False``).
        policy: a trained policy file (``policy.pt``) to roll out instead of the expert; it must fit the env.
        policy_runtime: its device, precision and compilation (default: the CPU at fp32, as ``dust-rl collect``'s);
            its threads are ``workers``'.
        wait_for_writer: when another process is collecting into ``root``, wait for it (then resume or find the
            data complete) instead of raising.

    Returns:
        the dataset metadata (``meta.json``).

    Raises:
        ConfigError: a bad count, seed or noise, an unknown task, env kwargs the env refuses, or noise with a
            policy (DART perturbs the expert).
        CheckpointError: a missing or corrupt policy file, or one that does not fit the env.
        DatasetError: ``root`` holds a collection with other settings.
        FolderLockedError: another process is collecting into ``root`` (and ``wait_for_writer`` is off).
    """
    tasks = list(dict.fromkeys(tasks))
    workers = workers if isinstance(workers, Workers) else Workers(workers)
    if not (isinstance(episodes, int) and episodes >= 1 and isinstance(workers.count, int) and workers.count >= 1):
        raise ConfigError(f"episodes and workers must be ints >= 1, got {episodes!r} and {workers.count!r}")
    if not (isinstance(start_seed, int) and start_seed >= 0) or not (math.isfinite(noise_std) and noise_std >= 0):
        raise ConfigError(f"start_seed must be an int >= 0 and noise_std a finite number >= 0, "
                          f"got {start_seed!r} and {noise_std!r}")
    check_seeds(start_seed, seeds_tried(policy, episodes) + workers.count)  # a worker may start one more
    if policy is not None and noise_std:
        raise ConfigError("noise_std perturbs the scripted expert's actions; a policy's rollouts take none")
    try:
        env_kwargs = json.loads(json.dumps(env_kwargs or {}))  # as it will read back from meta.json
    except (TypeError, ValueError) as err:
        raise ConfigError(f"env_kwargs must be JSON values (they are stored in meta.json): {err}") from err
    check_tasks(env_id, env_kwargs, tasks)
    probe = make_env(env_id, {**env_kwargs, "task": tasks[0]})
    spec = recorded_env_spec(probe)
    if not spec["cameras"]:
        probe.close()
        raise ConfigError("demonstrations need camera images and instructions: use obs_mode='rgb'")
    if policy is not None:
        policy = pathlib.Path(policy)
        load_policy(policy, env=make_torchrl_env(probe))  # raises before anything is written
    probe.close()
    actor = None if policy is None else {"file": policy.name, "sha256": _file_digest(policy)}
    config = {"env_id": env_id, "env_kwargs": env_kwargs, "start_seed": start_seed,
              "noise_std": float(noise_std), "keep_failed": keep_failed, "policy": actor}
    root = pathlib.Path(root)
    root.mkdir(parents=True, exist_ok=True)
    with (folder_lock(root, wait=wait_for_writer), ray_runtime(workers), torch_threads(workers.threads),
          no_space_left(f"collecting into {root}", "free some space and re-run the same command: the episodes "
                        "written so far are kept", clean=lambda: clear_staging(root))):
        clear_staging(root)
        meta = open_meta(root, config, tasks, episodes, spec)
        for task in tasks:
            target = meta["episodes_per_task"][task]
            if target > episodes:
                print(f"{root}: {task} already holds {target} episodes, more than the {episodes} asked; "
                      "keeping them all, nothing new to collect")
            _collect_task(root, env_id, {**env_kwargs, "task": task}, task, target, workers, start_seed,
                          noise_std, keep_failed, policy, policy_runtime or CPU_RUNTIME, progress)
        meta = finalize_dataset(root, progress)
        clear_staging(root)
    return meta


def demo_collector(env_id: str, env_kwargs: dict, workers: Workers, start_seed: int = 0,
                   known_seeds: frozenset[int] = frozenset(), noise_std: float = 0.0,
                   policy: pathlib.Path | None = None, policy_runtime: RuntimeSettings = CPU_RUNTIME,
                   ) -> contextlib.AbstractContextManager[BaseCollector]:
    """A torchrl collector yielding one whole episode ``[T]`` at a time, of the expert or of the trained
    ``policy`` (each remote worker loads its own copy) as ``policy_runtime`` runs it, seeds from ``start_seed`` on,
    ``known_seeds`` skipped (a context)."""
    env_fns = collection_env_fns(env_id, env_kwargs, start_seed, known_seeds, workers.count)
    if policy is None:
        return episode_collector(env_fns, workers, policy=make_expert_policy(noise_std))
    in_process = workers.count == 1 and workers.backend == "local"
    load = functools.partial(load_rollout_policy, policy, policy_runtime)
    return episode_collector(env_fns, workers, policy=load() if in_process else None,
                             policy_factory=None if in_process else load,
                             policy_device=str(resolve_device(policy_runtime.device)))


def _collect_task(root: pathlib.Path, env_id: str, env_kwargs: dict, task: str, episodes: int, workers: Workers,
                  start_seed: int, noise_std: float, keep_failed: bool, policy: pathlib.Path | None,
                  policy_runtime: RuntimeSettings, progress: bool) -> None:
    records = scan_episodes(root).get(task, {})
    if select_episodes(records, start_seed, episodes, keep_failed) is not None:
        return
    actor = "expert" if policy is None else "policy"
    with (demo_collector(env_id, env_kwargs, workers, start_seed, frozenset(records), noise_std,
                         policy, policy_runtime) as collector,
          tqdm(total=episodes, initial=_successes(records), desc=f"collecting {task}", disable=not progress) as bar):
        for trajectory in collector:
            rows, record = trajectory_to_episode(trajectory, task)
            keep = record.success or keep_failed
            records[record.seed] = write_episode(root, record, rows if keep else None)
            bar.update(min(_successes(records), episodes) - bar.n)
            if select_episodes(records, start_seed, episodes, keep_failed) is not None:
                return
            if len(records) >= seeds_tried(policy, episodes):
                raise SuccessesOutOfReachError(
                    f"the {task} {actor} succeeded in only {_successes(records)} of {len(records)} episodes; "
                    f"{episodes} successes are out of reach (the episodes so far are kept): ask for fewer (collect "
                    f"--episodes, finetune --rollout-successes){' or train the policy further' if policy else ''}")


def _successes(records: dict[int, EpisodeRecord]) -> int:
    return sum(record.success for record in records.values())


def _file_digest(path: pathlib.Path) -> str:
    """SHA-256 of a file's bytes."""
    return hashlib.sha256(path.read_bytes()).hexdigest()
