"""Scratch files: unnamed in their folder, short writes and reads resumed, a file that ends early and a full disk
are errors that say where."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import GdtError
from gdt_pipeline.scratch import read_at, scratch_file, write_at


def test_short_writes_and_reads_are_resumed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    values = np.random.default_rng(3).normal(size=(1000, 3, 3))
    real_write, real_read = os.pwrite, os.pread
    monkeypatch.setattr(os, "pwrite", lambda fd, data, offset: real_write(fd, bytes(data[:7]), offset))
    monkeypatch.setattr(os, "pread", lambda fd, size, offset: real_read(fd, min(size, 5), offset))
    with scratch_file(tmp_path, "t-") as f:
        assert os.listdir(tmp_path) == []
        write_at(f, values, 64, tmp_path, "test rows", "a few kB")
        back = read_at(f, values.dtype, values.shape, 64)
        assert np.array_equal(back, values)
        assert np.array_equal(read_at(f, values.dtype, (10, 3, 3), 64 + 990 * 72), values[990:])
        with pytest.raises(GdtError, match="ended after"):
            read_at(f, values.dtype, (11, 3, 3), 64 + 990 * 72)


def test_a_full_disk_names_the_folder_and_what_was_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int, data: object, offset: int) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", full)
    with scratch_file(tmp_path, "t-") as f, pytest.raises(GdtError) as err:
        write_at(f, np.zeros(10), 0, tmp_path, "test rows", "80 B")
    assert str(tmp_path) in str(err.value) and "test rows" in str(err.value) and "80 B" in str(err.value)
    assert "No space left" in str(err.value) and "TMPDIR" in str(err.value)
