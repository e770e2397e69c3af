"""The memory a process's C library holds free, handed back to the system.

glibc's malloc keeps memory a process freed in its heaps for the next allocation, and its
threshold for mapping a block of its own rises to the size of any mapped block freed (up to
32 MB), so the arrays of one phase of a store's group (a plan's rows, a unit's hits, the
chunks' bytes) end up in heaps that a later phase, asking for other sizes, cannot reuse: at
1 cm the process kept about 430 MB more than it used after a group (``docs/lidar.md``,
"Memory between a store's groups"). :func:`release_free_memory` hands what the heaps hold
free back to the system between phases (``malloc_trim``). :func:`libc` loads the C library
for it and for the other calls the store and the service make into it (``syncfs``,
``mallopt``, ``prctl``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["libc", "release_free_memory"]


@functools.cache
def libc() -> ctypes.CDLL | None:
    """The C library (with ``errno`` kept for ``ctypes.get_errno``), or None where it cannot
    be loaded. The one place the store and the service load it."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


def release_free_memory() -> bool:
    """Give the memory malloc holds free back to the system (glibc's ``malloc_trim(0)``);
    False where the C library has no ``malloc_trim`` (not glibc)."""
    trim = getattr(libc(), "malloc_trim", None)
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True
