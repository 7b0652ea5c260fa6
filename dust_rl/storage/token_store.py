"""Row-major float16 token files on disk, written as a stream and read memory-mapped.

Why: a dataset's cached frozen features can outgrow the machine's memory (2,000 pick_place
episodes at 2 x 8x8x112 tokens per row already take 1.6 GB), so they are never held whole in memory:
encoding appends one batch of rows at a time to the file, and training reads it through a memory
map, so the OS pages in the rows a batch needs and can drop them again (they count as page cache,
not as the process's own memory). The file is NumPy's ``.npy`` format (its header states dtype and
shape; read with ``allow_pickle=False``), written beside its final name and renamed when complete,
so a killed encoder never leaves a partial cache behind.
"""

from __future__ import annotations

import pathlib
from collections.abc import Iterable

import numpy as np
import torch

from dust_rl.errors import DatasetError
from dust_rl.storage.atomic_files import atomic_write

DTYPE = np.dtype("<f2")


def write_rows(path: pathlib.Path, shape: tuple[int, ...], batches: Iterable[torch.Tensor]) -> None:
    """Write ``batches`` (float16 tensors [rows_b, *shape[1:]], in order) as one ``.npy`` file of ``shape``.

    Raises:
        ValueError: the batches do not add up to ``shape`` (nothing is written).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = 0
    with atomic_write(path, "wb") as file:
        np.lib.format.write_array_header_1_0(file, {"descr": np.lib.format.dtype_to_descr(DTYPE),
                                                    "fortran_order": False, "shape": tuple(shape)})
        for batch in batches:
            if tuple(batch.shape[1:]) != tuple(shape[1:]) or batch.dtype != torch.float16:
                raise ValueError(f"a batch of shape {tuple(batch.shape)} ({batch.dtype}) for a file of rows "
                                 f"{tuple(shape[1:])} float16")
            file.write(batch.contiguous().numpy().astype(DTYPE, copy=False).tobytes())
            rows += len(batch)
        if rows != shape[0]:
            raise ValueError(f"{rows} rows written for a file of {shape[0]}")


def read_rows(path: pathlib.Path, shape: tuple[int, ...]) -> torch.Tensor:
    """The tokens in ``path``, memory-mapped (copy-on-write: writing to the tensor never changes the file).

    Raises:
        DatasetError: the file is truncated, not a ``.npy`` file, or holds another shape or dtype.
    """
    try:
        array = np.load(path, mmap_mode="c", allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise DatasetError(f"{path}: unreadable token cache ({err}); delete the file to rebuild it") from err
    if array.shape != tuple(shape) or array.dtype != DTYPE:
        raise DatasetError(f"{path}: token cache of shape {array.shape} ({array.dtype}), expected {tuple(shape)} "
                           "float16; delete the file to rebuild it")
    return torch.from_numpy(array)
