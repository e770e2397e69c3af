"""glibc's malloc thresholds of the service's processes (service/_malloc.py)."""

from __future__ import annotations

import ctypes
import ctypes.util

from rangefuse.service._malloc import MMAP_THRESHOLD, TUNABLES, tune_malloc, with_tunables


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost",
    )]  # fmt: skip


def test_blocks_below_the_threshold_come_from_the_heap():
    assert tune_malloc()  # glibc: mallopt took both
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    libc.mallinfo2.restype = _MallInfo2

    def mapped_by(size: int) -> int:
        """Bytes of mmapped blocks that a block of ``size`` adds."""
        before = libc.mallinfo2().hblkhd
        block = libc.malloc(size)
        try:
            return int(libc.mallinfo2().hblkhd - before)
        finally:
            libc.free(block)

    assert mapped_by(MMAP_THRESHOLD * 3 // 4) == 0  # a 12 MiB range map: the heap
    assert mapped_by(MMAP_THRESHOLD * 3 // 2) >= MMAP_THRESHOLD * 3 // 2  # mapped, as before


def test_children_get_them_unless_the_environment_says_otherwise():
    assert with_tunables({"A": "1"}) == {"A": "1", "GLIBC_TUNABLES": TUNABLES}
    mine = {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}
    assert with_tunables(mine) == mine
