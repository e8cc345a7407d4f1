"""Keep the C heap from holding freed whole images (glibc only): the hires camera's memory (issue 16, item 5).

A view's work allocates and frees many whole-image arrays (a 5 MP camera's float32 image is 20 MB, its
bool or uint8 one 5 MB; the decode's bands of 256 rows 2.5-5 MB). glibc serves blocks below its mmap
threshold from its heaps, and raises that threshold to the size of each large block freed (up to 32 MB), so
after the first views nearly every image is in a heap; a heap gives memory back only from its top, so the
images freed below the arrays a view keeps stay resident: much of the ~65 MB a view the hires pillar's
process grew by over its feedback views (docs/benchmarks.md, "Peak memory of a whole inspection").
:func:`map_large_arrays` fixes the threshold (blocks from 8 MiB on get mappings of their own, returned when
freed); :func:`release_free_heap` returns the free whole pages of every arena (the main thread's and the
decode worker's) between views. No Python library exposes either, hence ctypes. Elsewhere (musl, macOS,
Windows) both are no-ops: those allocators manage their memory on their own terms.
"""

from __future__ import annotations

import ctypes
import sys
from collections.abc import Callable

__all__ = ["HEAP_ARRAY_LIMIT_BYTES", "map_large_arrays", "release_free_heap"]


def _glibc() -> ctypes.CDLL | None:
    """The running process's C library when it is glibc (Linux), else None (musl has no
    ``gnu_get_libc_version``; other systems are not looked at)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018  # glibc only: musl has no such symbol
    except (OSError, AttributeError):
        return None
    return libc


_LIBC = _glibc()
_MALLOC_TRIM: Callable[[int], int] | None = None
_MALLOPT: Callable[[int, int], int] | None = None
if _LIBC is not None:
    _MALLOC_TRIM = _LIBC.malloc_trim
    _MALLOC_TRIM.argtypes = [ctypes.c_size_t]
    _MALLOC_TRIM.restype = ctypes.c_int
    _MALLOPT = _LIBC.mallopt
    _MALLOPT.argtypes = [ctypes.c_int, ctypes.c_int]
    _MALLOPT.restype = ctypes.c_int

# glibc's mallopt parameter for the mmap threshold (malloc.h), and the value set: blocks of 8 MiB and more (a
# 5 MP camera's float32 or int16 images, its float64 ones) get mappings of their own, returned to the system
# when freed; smaller ones (the decode's bands of 256 rows, 5 MB) stay in the heaps, which reuse them. Lower
# thresholds cost system time for every fresh page: at 1 MiB a hires run's system CPU tripled (200 -> 673 s).
_M_MMAP_THRESHOLD = -3
HEAP_ARRAY_LIMIT_BYTES = 8 * 1024 * 1024


def map_large_arrays() -> bool:
    """Give every block of :data:`HEAP_ARRAY_LIMIT_BYTES` or more a mapping of its own (glibc's
    ``mallopt(M_MMAP_THRESHOLD)``; it also stops glibc raising the threshold to 32 MB as large blocks are
    freed), so the heaps do not fill with the free gaps whole images leave between the arrays a view keeps.
    For the whole process; True if set, False where the C library is not glibc."""
    if _MALLOPT is None:
        return False
    return bool(_MALLOPT(_M_MMAP_THRESHOLD, HEAP_ARRAY_LIMIT_BYTES))


def release_free_heap() -> bool:
    """Return the C heap's free pages to the system (``malloc_trim(0)``, every arena); True if glibc gave any
    back, False if none or not glibc. Safe from any thread and at any time: it frees nothing in use."""
    if _MALLOC_TRIM is None:
        return False
    return bool(_MALLOC_TRIM(0))
