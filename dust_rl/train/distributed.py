"""Data-parallel training over processes: ``dust-rl train --runtime.nproc N`` or ``torchrun --nproc-per-node N -m
dust_rl.train.imitation ...``, with PyTorch's ``DistributedDataParallel``.

How the work is split, and why: every rank seeds torch's global generator alike and so draws the same
global batch of windows each step; each keeps its own contiguous slice of it (:meth:`Ranks.shard`), and
the flow-matching noise is drawn for the whole batch and sliced the same way
(:class:`dust_rl.agents.model.flow_matching.Shard`). Every sample thus gets the window and noise it gets in one
process with the same global batch, the generators of all ranks stay equal (a resumed run restores one
state for all), and ``DistributedDataParallel`` averages the ranks' gradients. Losses are means over each
rank's valid (unpadded) actions, so the averaged gradient equals the one-process gradient up to rounding
when the ranks' slices hold as many valid actions, and weights padded rows slightly differently otherwise.

Rank 0 writes everything (config, checkpoints, logs, ``policy.pt``, periodic evaluations); every rank
keeps the EMA, identical on all. Backends: gloo on the CPU, NCCL on CUDA with rank r on ``cuda:LOCAL_RANK``.
On one machine's CPU cores this buys no speed (2 processes on 2 cores share them); it is the same code
path a GPU node uses.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from dust_rl.agents.model.flow_matching import Shard
from dust_rl.errors import UserError

# What torchrun sets, and what :func:`spawn` sets for the processes it starts.
ENV_KEYS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


class RanksDivergedError(RuntimeError):
    """The ranks of a data-parallel run ended with different weights: a bug, not a user error."""


class RankFailedError(UserError):
    """A process of a ``--runtime.nproc`` run stopped with an error (its message follows)."""


@dataclass(frozen=True)
class Ranks:
    """This process's place in the run: one process unless it was started by torchrun or `spawn()`."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """Whether this process writes the run's files."""
        return self.rank == 0

    @property
    def shard(self) -> Shard:
        """This rank's part of every global batch."""
        return Shard(self.rank, self.world_size)

    def barrier(self) -> None:
        """Wait for every rank (no-op in one process)."""
        if self.world_size > 1:
            dist.barrier()

    def mean(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` averaged over the ranks (the same tensor in one process)."""
        if self.world_size == 1:
            return values
        total = values.detach().clone()
        dist.all_reduce(total)
        return total / self.world_size

    def check_same(self, weights: torch.Tensor) -> None:
        """Raise unless every rank holds exactly these ``weights`` (a flat tensor).

        Raises:
            RanksDivergedError: some rank's weights differ.
        """
        if self.world_size == 1:
            return
        gathered = [torch.empty_like(weights) for _ in range(self.world_size)]
        dist.all_gather(gathered, weights)
        differ = [rank for rank, other in enumerate(gathered) if not torch.equal(other, gathered[0])]
        if differ:
            raise RanksDivergedError(f"ranks {differ} hold weights other than rank 0's after training")


def join_process_group(device: torch.device) -> Ranks:
    """This process's :class:`Ranks`, joining the process group that torchrun's (or :func:`spawn`'s)
    environment describes; without one (``WORLD_SIZE`` unset or 1), a single process."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size == 1:
        return Ranks()
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(local_rank)  # NCCL's collectives run on each rank's own GPU
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return Ranks(dist.get_rank(), dist.get_world_size(), local_rank)


def rank_device(device: torch.device, ranks: Ranks) -> torch.device:
    """The device of this rank: its own GPU (``cuda:LOCAL_RANK``) when training on CUDA, else ``device``."""
    return torch.device("cuda", ranks.local_rank) if device.type == "cuda" and ranks.world_size > 1 else device


def data_parallel(module: nn.Module, ranks: Ranks) -> nn.Module:
    """``module`` wrapped in ``DistributedDataParallel`` when there are several ranks (itself otherwise).

    Its frozen parameters take no part in the gradient averaging; buffers are synchronised once, not every
    step (the trained modules hold none that change, and the frozen backbone's are equal on every rank)."""
    if ranks.world_size == 1:
        return module
    device = next(module.parameters()).device
    return DistributedDataParallel(module, device_ids=[device] if device.type == "cuda" else None,
                                   forward_sync_buffers=False)


def leave_process_group() -> None:
    """Leave the process group, if this process is in one."""
    if dist.is_initialized():
        dist.destroy_process_group()


def spawn(nproc: int, fn: Callable[..., object], *args: object) -> object:
    """Run ``fn(*args)`` in ``nproc`` new processes that form one process group on this machine; returns
    rank 0's result.

    Raises:
        RankFailedError: a process raised; the message is its error's.
    """
    results = mp.get_context("spawn").SimpleQueue()
    try:
        mp.start_processes(_run_rank, args=(nproc, _free_port(), fn, args, results), nprocs=nproc,
                           start_method="spawn")
    except mp.ProcessRaisedException as err:
        last = str(err).strip().splitlines()[-1]
        raise RankFailedError(f"a process of the {nproc}-process run failed: {last}") from err
    return results.get()


def _run_rank(rank: int, nproc: int, port: int, fn: Callable[..., object], args: tuple,
              results: mp.SimpleQueue) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(nproc), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    result = fn(*args)
    if rank == 0:
        results.put(result)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
