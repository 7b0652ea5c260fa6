"""Token files: streamed writes, memory-mapped reads, and clear errors for broken files."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import torch

from dust_rl.data import DatasetError
from dust_rl.storage.token_store import read_rows, write_rows

SHAPE = (7, 2, 3)


def batches(*sizes: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return [torch.randn(n, *SHAPE[1:], generator=generator).half() for n in sizes]


def test_rows_written_in_batches_read_back_memory_mapped(tmp_path):
    path = tmp_path / "features" / "tokens.npy"
    written = batches(3, 4)
    write_rows(path, SHAPE, iter(written))
    rows = read_rows(path, SHAPE)
    assert torch.equal(rows, torch.cat(written))
    assert str(path) in pathlib.Path("/proc/self/maps").read_text()  # mapped, not read into memory
    rows.zero_()  # copy-on-write: the file keeps its tokens
    assert torch.equal(read_rows(path, SHAPE), torch.cat(written))
    assert [p.name for p in path.parent.iterdir()] == ["tokens.npy"]  # no temp file left


def test_batches_that_do_not_fill_the_file_leave_nothing(tmp_path):
    path = tmp_path / "tokens.npy"
    with pytest.raises(ValueError, match="6 rows written for a file of 7"):
        write_rows(path, SHAPE, iter(batches(3, 3)))
    with pytest.raises(ValueError, match="batch of shape"):
        write_rows(path, SHAPE, iter([torch.zeros(7, 2, 4, dtype=torch.float16)]))
    assert not list(tmp_path.iterdir())


def test_broken_files_are_refused_by_name(tmp_path):
    path = tmp_path / "tokens.npy"
    write_rows(path, SHAPE, iter(batches(7)))
    with pytest.raises(DatasetError, match=r"shape \(7, 2, 3\) \(float16\), expected \(7, 2, 4\)"):
        read_rows(path, (7, 2, 4))
    path.write_bytes(path.read_bytes()[:-10])  # truncated
    with pytest.raises(DatasetError, match="unreadable token cache.*delete the file"):
        read_rows(path, SHAPE)
    path.write_bytes(b"not a numpy file")
    with pytest.raises(DatasetError, match="unreadable token cache"):
        read_rows(path, SHAPE)
    np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)  # would need unpickling: refused
    with pytest.raises(DatasetError, match="unreadable token cache"):
        read_rows(path, SHAPE)
