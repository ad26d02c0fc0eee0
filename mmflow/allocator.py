"""Keep freed memory in the process for reuse: fixed glibc malloc thresholds.

The transfer, normal and solve kernels allocate and free arrays of 1-30 MB per m and per
ring (Legendre tables, Fourier rings, per-m blocks). glibc's default *dynamic* thresholds
learn from such frees and serve the next array from memory the process already holds.
``distributed`` starts its worker processes with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``), which fixes the trim threshold at 64 kB and
switches the dynamic adjustment off: every array above 128 kB is then a fresh ``mmap`` whose
pages fault in on first touch and go back to the kernel on free, and a worker takes longer than
a plain process for the same work (figures: ``docs/performance.md``).

:func:`keep_freed_memory` sets both thresholds explicitly (``mallopt``), once per process:
arrays up to ``mmap_mb`` come from the heap, and up to ``trim_mb`` of freed heap stays
mapped for the next allocation. The results do not depend on it (same bits); the process's
resident memory may stay up to ``trim_mb`` above what it uses. A no-op where the C library
is not glibc.

Freed memory can also stay resident *inside* the heap (arrays below ``mmap_mb`` freed among
others still held: fragmentation), which no trim threshold returns: a worker that ran the
paper channel's transfer tasks began the next with 5.3 GB resident and peaked at 8.6 GB, and
began CLEAN with 6 GB. :func:`release_freed_memory` (glibc ``malloc_trim(0)``, which also gives
back the free pages inside the heap) returns it; measured here: 4.5 GB of 20 MB arrays in 85 ms,
0.1 ms when there is nothing to return.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
from functools import lru_cache

#: glibc's ``mallopt`` parameter numbers (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: glibc caps the mmap threshold at 32 MiB on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``)
MMAP_MB = 32
TRIM_MB = 256


@lru_cache(maxsize=1)
def keep_freed_memory(mmap_mb=MMAP_MB, trim_mb=TRIM_MB):
    """Set glibc's mmap threshold to ``mmap_mb`` and its trim threshold to ``trim_mb`` (once).

    ``MMFLOW_MALLOC=default`` leaves the allocator as the process started it.

    Returns
    -------
    bool
        True where the thresholds were set.
    """
    if os.environ.get("MMFLOW_MALLOC", "") == "default":
        return False
    libc = _glibc()
    if libc is None:
        return False
    ok_mmap = libc.mallopt(M_MMAP_THRESHOLD, int(mmap_mb) << 20)
    ok_trim = libc.mallopt(M_TRIM_THRESHOLD, int(trim_mb) << 20)
    return bool(ok_mmap and ok_trim)


@lru_cache(maxsize=1)
def _glibc():
    """The process's C library if it is glibc (it has ``gnu_get_libc_version``), else None."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 -- AttributeError off glibc (musl, macOS)
    except (OSError, AttributeError):
        return None
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    return libc


def release_freed_memory():
    """Give the free pages of every heap back to the kernel (glibc ``malloc_trim(0)``).

    Returns
    -------
    bool
        True where memory was released (False: nothing to release, or not glibc).
    """
    libc = _glibc()
    return bool(libc is not None and libc.malloc_trim(0))
