"""Disk space for memory-mapped writes, claimed before they start.

Memory-mapped files are written through their pages: on a full disk the kernel answers such a write with
SIGBUS, which kills the process with no message and no clean-up, instead of an ``OSError`` it could report.
Datasets and checkpoints are written this way (tensordict's memmaps), so their writers claim the space first.
"""

from __future__ import annotations

import errno
import os
import pathlib
import shutil


def reserve_space(path: pathlib.Path, nbytes: int) -> None:
    """Raise ``OSError`` (ENOSPC) unless the file system of ``path`` has ``nbytes`` free."""
    free = shutil.disk_usage(path).free
    if free < nbytes:
        raise OSError(errno.ENOSPC, f"{nbytes} bytes needed, {free} free", str(path))


def allocate_files(folder: pathlib.Path) -> None:
    """Give every file under ``folder`` (a fresh memmap folder, whose files are sparse) its disk blocks now,
    so a full disk fails here with ``OSError`` (ENOSPC) rather than as SIGBUS when a page is written."""
    for file in sorted(p for p in folder.rglob("*") if p.is_file()):
        size = file.stat().st_size
        if size:
            fd = os.open(file, os.O_RDWR)
            try:
                os.posix_fallocate(fd, 0, size)
            finally:
                os.close(fd)
