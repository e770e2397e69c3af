"""Arrays reused from one scan to the next of a batch.

Each scan needs a few arrays of megabytes for a moment: allocation's pixel ranges, node
pyramid and key room (engine.tiling), the per-quad bounds (engine._sampling). Fresh ones
cost page faults on first touch (about 0.5 us a page in the VMs we measure on: 450 faults,
a quarter of a millisecond, per 640 x 480 frame in allocation alone), and the allocator
hands memory back between frames. A batch (:meth:`engine.fusion.Volume.add_many`) keeps
one :class:`Scratch` for all its scans instead. Not shared between threads.
"""

from __future__ import annotations

import numpy as np


class Scratch:
    """Named arrays, reused while the shape and dtype asked for stay the same."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, shape: tuple[int, ...], dtype: type | np.dtype) -> np.ndarray:
        """An uninitialised array ``name`` of ``shape`` and ``dtype`` (the previous one when
        they match: its contents are whatever the last user left)."""
        shape = tuple(int(n) for n in shape)
        dtype = np.dtype(dtype)
        a = self._arrays.get(name)
        if a is None or a.shape != shape or a.dtype != dtype:
            a = np.empty(shape, dtype)
            self._arrays[name] = a
        return a


def array(scratch: Scratch | None, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """``scratch.array(...)``, or a fresh array without a scratch."""
    if scratch is None:
        return np.empty(tuple(int(n) for n in shape), dtype)
    return scratch.array(name, shape, dtype)
