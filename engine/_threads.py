"""Which numba threading layer runs the parallel kernels, and a warning when it is the slow one.

numba's PyPI wheels take OpenMP from the system (``libgomp.so.1``). Where it is missing
(slim container images, minimal installs) numba falls back to its ``workqueue`` layer
without a word, and fusion runs much slower: on the 2-core benchmark machine, 100 room
frames ran at 95-142 frames/s at 2 cm and 50-55 at 1 cm on ``workqueue``, against 162-193
and 62-71 on ``omp`` (alternated fresh processes).
"""

from __future__ import annotations

import functools
import warnings

import numba
import numpy as np
from numba import njit, prange

__all__ = ["threading_layer", "warn_if_slow_threading"]


@njit(cache=True, parallel=True)
def _touch(out):
    for i in prange(out.shape[0]):
        out[i] = i


def threading_layer() -> str:
    """The numba threading layer of this process (``omp``, ``tbb`` or ``workqueue``); runs
    a tiny parallel kernel first, since numba picks the layer at the first one."""
    _touch(np.zeros(2, np.int64))
    return str(numba.threading_layer())


@functools.cache
def warn_if_slow_threading() -> None:
    """Warn once per process when numba fell back to its ``workqueue`` layer on its own
    (not when ``NUMBA_THREADING_LAYER`` asked for it) and has more than one thread."""
    asked = getattr(numba.config, "THREADING_LAYER", "default")  # set from the environment
    if asked != "default" or numba.get_num_threads() < 2:
        return
    if threading_layer() == "workqueue":
        warnings.warn(
            "numba runs rangefuse's kernels on its 'workqueue' threading layer because "
            "neither OpenMP (libgomp.so.1) nor TBB could be loaded; fusion is about 1.4x "
            "slower. Install libgomp1 (Debian, Ubuntu: apt-get install libgomp1) or "
            "'pip install tbb'.",
            RuntimeWarning,
            stacklevel=3,
        )
