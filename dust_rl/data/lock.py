"""One writer per dataset folder: an exclusive ``flock`` on a lock file inside it.

Two collections writing into one folder clear each other's staging files and race
on ``meta.json`` (a task can vanish from the request, or a write fails with
``OSError``). The lock is held for the whole collection; the kernel releases it when
the process ends, however it ends, so a killed collection never leaves a stale lock.
The holder writes who it is (pid, host, command, start time) into the file, so a
refused process can say which one holds it. A caller that only needs the data
to be there (``dust-rl bench suite``, two of which often share a folder) waits
for the holder instead of failing.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import json
import os
import pathlib
import shlex
import socket
import sys
from collections.abc import Iterator

from dust_rl.errors import UserError

LOCK_FILE = ".lock"


class DatasetLockedError(UserError):
    """Another process is writing into the dataset folder."""


@contextlib.contextmanager
def dataset_lock(root: pathlib.Path, wait: bool = False) -> Iterator[None]:
    """Hold the write lock of the dataset folder ``root`` (which must exist) for the ``with`` body.

    Args:
        wait: when another process holds it, say so on stderr and wait until it lets go.

    Raises:
        DatasetLockedError: another process holds it and ``wait`` is off; the message names that process.
    """
    path = root / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            message = f"{root} is being written by another process ({_holder(path)})"
            if not wait:
                raise DatasetLockedError(f"{message}; wait for it to finish or stop it") from None
            print(f"{message}; waiting for it to finish", file=sys.stderr, flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": shlex.join(sys.orig_argv),
                  "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with the next locker)


def _holder(path: pathlib.Path) -> str:
    """Who holds the lock, as written into the lock file."""
    try:
        holder = json.loads(path.read_text())
        return f"pid {holder['pid']} on {holder['host']}, started {holder['started']}: {holder['command']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "it has not written its details yet"
