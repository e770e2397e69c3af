"""glibc's malloc thresholds of the service's processes (service/_malloc.py), and the free
memory handed back between a store's groups (storage/_heap.py)."""

from __future__ import annotations

import subprocess
import sys

from rangefuse.service._malloc import TUNABLES, with_tunables

#: Run in a fresh interpreter: a heap that earlier tests left with big free blocks serves
#: any size from them, mapped or not.
_CHECK = """
import ctypes, ctypes.util
from rangefuse.service._malloc import MMAP_THRESHOLD, tune_malloc

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

assert tune_malloc()  # glibc: mallopt took both
libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
libc.mallinfo2.restype = MallInfo2

def mapped_by(size):
    before = libc.mallinfo2().hblkhd
    block = libc.malloc(size)
    try:
        return libc.mallinfo2().hblkhd - before
    finally:
        libc.free(block)

print(mapped_by(MMAP_THRESHOLD * 3 // 4), mapped_by(MMAP_THRESHOLD * 3 // 2))
"""


def test_blocks_below_the_threshold_come_from_the_heap():
    out = subprocess.run([sys.executable, "-c", _CHECK], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    small, big = (int(x) for x in out.stdout.split())
    assert small == 0  # a 12 MiB range map: from the heap, kept for the next one
    assert big >= 24 * 2**20  # 24 MiB: mapped and unmapped, as before


def test_children_get_them_unless_the_environment_says_otherwise():
    assert with_tunables({"A": "1"}) == {"A": "1", "GLIBC_TUNABLES": TUNABLES}
    mine = {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}
    assert with_tunables(mine) == mine


#: Free blocks below one still in use: the heap cannot shrink from its top, and only
#: ``malloc_trim`` hands the pages between back.
_TRIM = """
import ctypes
from rangefuse.storage._heap import libc, release_free_memory

c = libc()
c.malloc.restype = ctypes.c_void_p
c.malloc.argtypes = [ctypes.c_size_t]
c.free.argtypes = [ctypes.c_void_p]

def rss():
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmRSS"))

blocks = [c.malloc(4000) for _ in range(50_000)]  # 200 MB in blocks below the thresholds
for b in blocks:
    ctypes.memset(b, 1, 4000)
top = c.malloc(4000)  # in use above them
for b in blocks:
    c.free(b)
before = rss()
assert release_free_memory()
print(before - rss())
"""


def test_free_memory_below_a_block_in_use_goes_back_to_the_system():
    out = subprocess.run([sys.executable, "-c", _TRIM], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) > 150 * 2**20  # of the 200 MB freed
