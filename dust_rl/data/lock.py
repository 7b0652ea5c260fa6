"""One writer per dataset folder: an exclusive ``flock`` on a lock file inside it.

Two collections writing into one folder clear each other's staging files and race
on ``meta.json`` (a task can vanish from the request, or a write fails with
``OSError``). The lock is held for the whole collection; the kernel releases it when
the process ends, however it ends, so a killed collection never leaves a stale lock.
The holder writes who it is (pid, host, command, start time) into the file, so a
refused process can say which one holds it.
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
def dataset_lock(root: pathlib.Path) -> Iterator[None]:
    """Hold the write lock of the dataset folder ``root`` (which must exist) for the ``with`` body.

    Raises:
        DatasetLockedError: another process holds it; the message names that process.
    """
    path = root / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DatasetLockedError(f"{root} is being written by another process ({_holder(path)}); "
                                     "wait for it to finish or stop it") from None
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
