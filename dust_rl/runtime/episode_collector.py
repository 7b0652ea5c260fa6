"""The torchrl collector behind ``dust-rl eval`` and ``dust-rl collect``: whole episodes, here or on Ray.

Both commands consume one whole episode at a time (``trajs_per_batch=1``,
``traj_format="cat"``) and key everything by the episode's seed, so where the
episodes run does not change what they are: ``workers`` env processes on this
machine (torchrl's process backend), or ``workers`` Ray actors
(``Collector(backend="ray")``, torchrl's ``RayCollector``) on a local Ray cluster
started for the command, or on an existing one (``ray_address``). Ray is an
optional extra (``pip install "dust-rl[ray]"``).

Measured on this 2-core machine (BENCHMARKS.md "Scaling", 20 pick_place
episodes): 2 Ray actors run episodes as fast as 2 local processes (1.73 vs 1.64
episodes/s) and the same episodes, digest for digest, but starting the local
cluster adds ~3 s to the command; Ray pays off when it spreads episodes over a
cluster.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterator, Sequence

import torch
from torchrl.collectors import BaseCollector, Collector
from torchrl.envs import EnvBase

from dust_rl.runtime.workers import Workers

# One frame batch per worker: episodes are cut out of the stream by trajs_per_batch, not by batch size.
FRAMES_PER_WORKER = 32
# Each Ray actor asks for this much memory (a worker with a policy, a MuJoCo scene and its renderer peaks at ~1 GiB).
RAY_ACTOR_MEMORY = 2 * 1024**3
# "Never stop": the consumer breaks out once it has its episodes.
UNBOUNDED_FRAMES = 2**62


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run with ``n`` torch threads (a policy acting in this process), then restore the caller's count."""
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@contextlib.contextmanager
def episode_collector(env_fns: Sequence[Callable[[], EnvBase]], workers: Workers, *,
                      policy: Callable | None = None, policy_factory: Callable[[], Callable] | None = None,
                      policy_device: str = "cpu") -> Iterator[BaseCollector]:
    """A collector yielding one whole episode ``[T]`` at a time from ``env_fns`` (one per worker), shut down
    when the block ends.

    Args:
        env_fns: one env constructor per worker (each with its own seed schedule).
        workers: how many, and where.
        policy: the policy of a single in-process worker, and of every worker when no ``policy_factory`` is given
            (then it is pickled to them).
        policy_factory: builds each remote worker's policy there (e.g. from a checkpoint file).
        policy_device: where the policy runs; observations go there and actions come back to the CPU.
    """
    if len(env_fns) != workers.count:
        raise ValueError(f"{len(env_fns)} env constructors for {workers.count} workers")
    per_episode = {"trajs_per_batch": 1, "traj_format": "cat", "trust_policy": True,
                   "auto_register_policy_transforms": False}
    if torch.device(policy_device).type != "cpu":
        per_episode |= {"policy_device": policy_device, "env_device": "cpu", "storing_device": "cpu"}
    remote_policy = {"policy_factory": policy_factory} if policy_factory is not None else {"policy": policy}
    if workers.backend == "ray":
        on_gpu = torch.device(policy_device).type == "cuda"
        actor = {"num_cpus": workers.threads, "num_gpus": 1 / workers.count if on_gpu else None,
                 "memory": RAY_ACTOR_MEMORY}
        source = {"create_env_fn": list(env_fns), **remote_policy, "backend": "ray",
                  "num_collectors": workers.count, "sync": False,
                  "backend_options": {"collector_kwargs": per_episode, "remote_configs": actor},
                  # torchrl 0.14.1's RayCollector stops at once on total_frames=-1 (it compares frames < -1).
                  "total_frames": UNBOUNDED_FRAMES}
        per_episode = {}
    elif workers.count == 1:
        source = {"create_env_fn": env_fns[0], "policy": policy}
    else:
        source = {"create_env_fn": list(env_fns), **remote_policy, "num_collectors": workers.count, "sync": False,
                  "num_threads": workers.threads, "num_sub_threads": workers.threads}
    with warnings.catch_warnings():
        # Every worker runs a fixed policy of its own: no weights are ever sent to workers, which torchrl warns of.
        for message in ("weight_updater is None", "The policy is not an nn.Module",
                        "RayCollector iteration started before weight synchronization"):
            warnings.filterwarnings("ignore", message=message)
        collector = Collector(**{"total_frames": -1, **source}, frames_per_batch=FRAMES_PER_WORKER * workers.count,
                              **per_episode)
        try:
            yield collector
        finally:
            collector.shutdown()
