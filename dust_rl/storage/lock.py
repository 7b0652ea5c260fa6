"""One writer per folder (a dataset, a training run): an exclusive ``flock`` on a lock file inside it.

Two collections writing into one folder clear each other's staging files and race
on ``meta.json`` (a task can vanish from the request, or a write fails with
``OSError``); two training runs in one folder interleave their logs and checkpoints.
The lock is held for the whole collection or run; the kernel releases it when
the process ends, however it ends, so a killed collection never leaves a stale lock.
The holder writes who it is (pid, host, command, start time) into the file, so a
refused process can say which one holds it. A caller that only needs the data
to be there (``dust-rl bench suite``, two of which often share a folder) waits
for the holder instead of failing. The lock file is opened without following a
symlink and must be a regular file with one link: a ``.lock`` symlink, or a hard link
to another file of the folder (hard links survive ``tar``, so a shipped folder can carry
one), would otherwise have the holder's details written over the file it points to.
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
import stat
import sys
from collections.abc import Iterator

from dust_rl.errors import UserError

LOCK_FILE = ".lock"


class FolderLockedError(UserError):
    """Another process is writing into the folder, or its lock file is not a plain file."""


class FolderBusyError(FolderLockedError):
    """Another process holds the folder's lock (the only :class:`FolderLockedError` that waiting would end)."""


@contextlib.contextmanager
def folder_lock(root: pathlib.Path, wait: bool = False) -> Iterator[None]:
    """Hold the write lock of the folder ``root`` (which must exist) for the ``with`` body.

    Args:
        wait: when another process holds it, say so on stderr and wait until it lets go.

    Raises:
        FolderBusyError: another process holds it and ``wait`` is off (the message names that process).
        FolderLockedError: the lock file is a symlink, a hard link or not a regular file, or cannot be opened.
    """
    path = root / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
    except OSError as err:
        raise FolderLockedError(f"{path}: cannot open the lock file ({err.strerror}); a symlink is refused, "
                                "remove it") from err
    try:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise FolderLockedError(f"{path}: the lock file is not a regular file; remove it")
        if status.st_nlink != 1:
            raise FolderLockedError(f"{path}: the lock file is a hard link ({status.st_nlink} names for one file), "
                                    "and taking the lock would overwrite the other names; remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            message = f"{root} is being written by another process ({_holder(fd)})"
            if not wait:
                raise FolderBusyError(f"{message}; wait for it to finish or stop it") from None
            print(f"{message}; waiting for it to finish", file=sys.stderr, flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": shlex.join(sys.orig_argv),
                  "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)  # no stale holder in a folder copied later
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with the next locker)


def _holder(fd: int) -> str:
    """Who holds the lock, as written into the lock file (read through its open descriptor)."""
    try:
        holder = json.loads(os.pread(fd, 1 << 16, 0))
        return f"pid {holder['pid']} on {holder['host']}, started {holder['started']}: {holder['command']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "it has not written its details yet"
