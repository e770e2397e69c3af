"""glibc's malloc set for buffers of a few megabytes (docs/service.md, "Upload throughput").

An upload's range map passes through several buffers of its size (the body, the decoded
array, the compressed chunk), and a fusion unit through tile blocks of a few megabytes.
glibc serves those from fresh ``mmap``s and hands freed memory back to the kernel at once (its
thresholds start at 128 KiB), so every upload faulted its pages in again: some 720 page faults
an upload of a 640 x 480 float32 map, about a third of the API process's CPU in the kernel.
With the thresholds below, blocks up to 16 MiB come from the heap and up to 64 MiB of free
heap is kept: 60 faults an upload. Bigger buffers are still mapped and unmapped as before.
"""

from __future__ import annotations

import ctypes

from rangefuse.storage._heap import libc

__all__ = ["TUNABLES", "tune_malloc", "with_tunables"]

#: Largest block served from the heap (bytes).
MMAP_THRESHOLD = 16 * 2**20
#: Free memory at the top of a heap kept before it is given back (bytes).
TRIM_THRESHOLD = 64 * 2**20
#: The same, for processes started from here (``GLIBC_TUNABLES``, read by glibc at start).
TUNABLES = (
    f"glibc.malloc.mmap_threshold={MMAP_THRESHOLD}:glibc.malloc.trim_threshold={TRIM_THRESHOLD}"
)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def tune_malloc() -> bool:
    """Set this process's thresholds (``mallopt``); False where the C library is not glibc."""
    mallopt = getattr(libc(), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )


def with_tunables(env: dict[str, str]) -> dict[str, str]:
    """``env`` for a child process, with :data:`TUNABLES` unless it sets ``GLIBC_TUNABLES``."""
    return env if "GLIBC_TUNABLES" in env else {**env, "GLIBC_TUNABLES": TUNABLES}
