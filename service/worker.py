"""Preload of a Dask worker that runs rangefuse's units of work (docs/scale-out.md)::

    dask worker tcp://scheduler:8786 --nthreads 1 --preload rangefuse.service.worker

Importing it (``rangefuse.service``) points numba's cache at the machine's one folder
before any kernel is loaded, so workers load the kernels that ``rangefuse warmup`` (or an
earlier worker) compiled instead of compiling them again. Set ``NUMBA_NUM_THREADS`` to the
cores each worker process may use (the service's own local workers get their share).
"""

from __future__ import annotations

import logging
import os

from . import numba_cache_dir

__all__ = ["dask_setup"]

log = logging.getLogger("rangefuse.worker")


def dask_setup(worker: object) -> None:
    """Called by Dask when the worker starts: say where kernels come from."""
    log.info(
        "rangefuse worker: numba cache %s, %s numba threads", numba_cache_dir(),
        os.environ.get("NUMBA_NUM_THREADS", "all cores"),
    )  # fmt: skip
