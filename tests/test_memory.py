"""cell.memory: fixing glibc's mmap threshold and giving the heap's free pages back are safe, repeatable, and
no-ops off glibc."""

from __future__ import annotations

import platform

import numpy as np
import pytest

from cell import memory


def test_release_free_heap_is_safe_and_repeatable() -> None:
    glibc = platform.libc_ver()[0] == "glibc"
    assert memory.map_large_arrays() is glibc and memory.map_large_arrays() is glibc  # mallopt says 1: set
    kept = np.arange(3_000_000, dtype=np.float64)  # 24 MB held across the calls
    for _ in range(3):
        freed = [np.full(1_000_000, 7.0) for _ in range(8)]  # heap-sized blocks, freed before the trim
        del freed
        assert isinstance(memory.release_free_heap(), bool)
    assert np.array_equal(kept, np.arange(3_000_000, dtype=np.float64))  # nothing in use was touched
    assert (memory._MALLOC_TRIM is not None) == glibc


def test_release_free_heap_is_a_no_op_without_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory.sys, "platform", "darwin")
    assert memory._glibc_malloc_trim() is None
    monkeypatch.setattr(memory, "_MALLOC_TRIM", None)
    monkeypatch.setattr(memory, "_MALLOPT", None)
    assert memory._glibc_mallopt() is None
    for _ in range(2):
        assert memory.release_free_heap() is False
        assert memory.map_large_arrays() is False
