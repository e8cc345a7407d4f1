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
    assert memory._glibc() is None
    monkeypatch.setattr(memory, "_MALLOC_TRIM", None)
    monkeypatch.setattr(memory, "_MALLOPT", None)
    for _ in range(2):
        assert memory.release_free_heap() is False
        assert memory.map_large_arrays() is False


# run in a fresh interpreter: the calls change the whole process's allocator (the threshold stays fixed)
_EFFECT = r"""
import ctypes, sys
from cell import memory

class Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Mallinfo2
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
MiB = 1 << 20

def mapped(): return libc.mallinfo2().hblkhd
def rss(): return int(open("/proc/self/statm").read().split()[1]) * 4096

if sys.argv[1] == "map":
    if sys.argv[2] == "set":
        memory.map_large_arrays()
    libc.free(libc.malloc(20 * MiB))  # glibc's own rule raises its threshold past 20 MiB on this free
    before = mapped()
    block = libc.malloc(16 * MiB)
    print(mapped() - before)
else:
    blocks = [libc.malloc(64 * 1024) for _ in range(1600)]  # 100 MiB of heap blocks (under the threshold)
    for b in blocks:
        ctypes.memset(b, 1, 64 * 1024)
    for b in blocks[:-1]:  # the last one pins the heap's top: only a trim gives the pages below it back
        libc.free(b)
    before = rss()
    if sys.argv[2] == "set":
        memory.release_free_heap()
    print(before - rss())
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_the_calls_change_what_glibc_does() -> None:
    """Without map_large_arrays a 16 MiB block comes from the heap once glibc raised its threshold; with it,
    it gets its own mapping. Without release_free_heap the freed pages below a held block stay resident;
    with it, they are given back."""
    import subprocess
    import sys

    def run(*args: str) -> int:
        cmd = [sys.executable, "-c", _EFFECT, *args]
        return int(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)

    mib = 1 << 20
    assert run("map", "unset") == 0 and run("map", "set") >= 16 * mib
    assert run("trim", "unset") < 5 * mib and run("trim", "set") > 80 * mib
