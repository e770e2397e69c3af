"""Memory for the engine's large arrays: working arrays reused across the scans of a batch,
and large arrays in ordinary pages.

*Scratch.* Each scan needs a few arrays of megabytes for a moment: allocation's pixel
ranges, node pyramid and key room (:mod:`engine.allocation`), the per-quad bounds
(:mod:`engine._sampling`). Fresh ones cost page faults on first touch (about 0.5 us a page
on the VMs we measure on: 450 faults, a quarter of a millisecond, per 640 x 480 frame in
allocation alone) and the allocator hands the memory back between frames. A batch
(:meth:`engine.fusion.Volume.add_many`) keeps one :class:`Scratch` for all its scans.

*Ordinary pages.* NumPy advises the kernel to back arrays of 4 MB and more with huge pages
(``madvise(MADV_HUGEPAGE)``). Where ``/sys/kernel/mm/transparent_hugepage/defrag`` is
``madvise`` (a common default) a fault in such memory may stall on synchronous compaction
when no huge page is free (numpy/numpy#31590). On our machines that made the first touch
of a 1 cm batch's 203 MB of tiles cost 300-450 ms instead of about 75 ms, and it varies
from run to run. :func:`zeros` gives large arrays anonymous ``mmap`` memory without that
advice: zero-filled, in ordinary pages.
"""

from __future__ import annotations

import math
import mmap

import numpy as np

#: Arrays at least this large come from :func:`zeros`' own mapping (NumPy's huge-page size).
LARGE_BYTES = 1 << 22


def zeros(shape: tuple[int, ...], dtype: type | np.dtype) -> np.ndarray:
    """A zeroed, writable array; a large one in ordinary pages (see the module's note)."""
    shape = tuple(int(n) for n in shape)
    dtype = np.dtype(dtype)
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes < LARGE_BYTES:
        return np.zeros(shape, dtype)
    return np.frombuffer(mmap.mmap(-1, nbytes), dtype).reshape(shape)


class Scratch:
    """Named working arrays, reused while the shape and dtype asked for stay the same.
    Not shared between threads."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, shape: tuple[int, ...], dtype: type | np.dtype) -> np.ndarray:
        """Array ``name`` of ``shape`` and ``dtype``: zeros when new, else whatever its last
        user left in it."""
        shape = tuple(int(n) for n in shape)
        dtype = np.dtype(dtype)
        a = self._arrays.get(name)
        if a is None or a.shape != shape or a.dtype != dtype:
            a = zeros(shape, dtype)
            self._arrays[name] = a
        return a


def scratch_array(
    scratch: Scratch | None, name: str, shape: tuple[int, ...], dtype: type | np.dtype
) -> np.ndarray:
    """``scratch.array(...)``, or a new array without a scratch."""
    if scratch is None:
        return zeros(shape, dtype)
    return scratch.array(name, shape, dtype)
