"""Preload of a Dask worker that runs rangefuse's units of work (docs/scale-out.md)::

    dask worker tcp://scheduler:8786 --nthreads 1 --preload rangefuse.service.worker

Importing it (``rangefuse.service``) points numba's cache at the machine's one folder
before any kernel is loaded, so workers load the kernels that ``rangefuse warmup`` (or an
earlier worker) compiled instead of compiling them again. Set ``NUMBA_NUM_THREADS`` to the
cores each worker process may use (the service's own local workers get their share).

A unit of a job runs as :class:`OnJob` (``service/jobs.py`` wraps each one): while numba
compiles a kernel the unit needs, which happens only when the cache holds no build of it,
the worker says so to the job's service as a Dask event on :data:`COMPILE_TOPIC`
(``{"job", "worker", "compiling"}``: true when the first kernel starts compiling, false
when it is done), and the service shows it on the job (``message``). The events go through
the scheduler, so workers on other machines report the same way.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from typing import Any

from . import numba_cache_dir

__all__ = ["COMPILE_TOPIC", "OnJob", "dask_setup", "load_kernels"]

log = logging.getLogger("rangefuse.worker")

#: The Dask event topic on which workers report compilations (see the module's note).
COMPILE_TOPIC = "rangefuse-compiling"


def dask_setup(worker: object) -> None:
    """Called by Dask when the worker starts: say where kernels come from, and whether the
    first units will compile them."""
    from .warmup import cache_note

    log.info(
        "rangefuse worker: numba cache %s, %s numba threads; %s", numba_cache_dir(),
        os.environ.get("NUMBA_NUM_THREADS", "all cores"), cache_note(),
    )  # fmt: skip
    load_kernels()


def load_kernels() -> None:
    """Import the engine and the store and load one kernel, in a process that will run units
    or plan them. The first unit of a worker imported zarr, numba and the engine (about a
    second), and numba set up its compiler on the first kernel it loaded (half a second
    holding the GIL, SciPy's import included): 2 to 3 s of CPU under the first job's
    uploads. Done when the process starts instead (a cold cache compiles this one small
    kernel here)."""
    import numpy as np
    import rangefuse.storage.units  # noqa: F401  (what units name: the store, the engine)
    from rangefuse.engine.grid import unique_keys

    unique_keys(np.zeros((1, 3), np.int64))


class OnJob:
    """``fn`` run on a unit of job ``job_id``: compilations the unit causes are reported on
    :data:`COMPILE_TOPIC` as the job's. Pickled to the worker with ``fn``."""

    def __init__(self, fn: Callable[[Any], Any], job_id: str) -> None:
        self.fn = fn
        self.job_id = job_id
        self.__name__ = getattr(fn, "__name__", type(fn).__name__)  # Dask names tasks by it

    def __call__(self, unit: Any) -> Any:
        _listen()
        _here.job_id = self.job_id
        _here.depth = 0
        try:
            return self.fn(unit)
        finally:
            if getattr(_here, "depth", 0) > 0:  # a compilation that never ended: it has now
                _here.depth = 0
                _report(False)
            _here.job_id = None


#: The unit running in this thread (``job_id``) and how deep the compilations in it nest
#: (``depth``: a kernel that calls another compiles it inside its own compilation).
_here = threading.local()
_listening = False
_listening_lock = threading.Lock()


def compilation_started() -> None:
    """A compilation starts in this thread: the outermost one is reported."""
    depth = getattr(_here, "depth", 0)
    _here.depth = depth + 1
    if depth == 0:
        _report(True)


def compilation_ended() -> None:
    """A compilation ends in this thread: the outermost one is reported."""
    depth = getattr(_here, "depth", 0)
    if depth <= 0:
        return
    _here.depth = depth - 1
    if depth == 1:
        _report(False)


def _report(compiling: bool) -> None:
    """Tell the service whether this thread's unit waits on a compilation (nothing outside a
    unit of a job, or outside a Dask worker)."""
    job_id = getattr(_here, "job_id", None)
    if job_id is None:
        return
    from distributed import get_worker

    try:
        worker = get_worker()
    except ValueError:  # not on a Dask worker
        return
    worker.log_event(
        COMPILE_TOPIC, {"job": job_id, "worker": str(worker.address), "compiling": compiling}
    )


def _listen() -> None:
    """Listen to numba's compilations in this process (once). numba announces a
    compilation only when its cache holds no build of the kernel for these argument types;
    loading a build from the cache is silent."""
    global _listening
    with _listening_lock:
        if _listening:
            return
        from numba.core import event

        class _Compilations(event.Listener):
            def on_start(self, ev: Any) -> None:
                compilation_started()

            def on_end(self, ev: Any) -> None:
                compilation_ended()

        event.register("numba:compile", _Compilations())
        _listening = True
