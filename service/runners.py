"""Runners: where units of work run (DESIGN.md "Scale-out").

:class:`storage.units.InProcess` runs them here; :class:`ProcessRunner` runs them on a pool
of worker processes started with ``spawn`` (numba's OpenMP layer breaks forked children),
each with its share of the machine's cores as numba threads. Results are bit-identical
either way: contributions are exact integers and every tile has one writer.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

from rangefuse.storage.units import TileUnit, UnitResult

__all__ = ["ProcessRunner", "spawn_pool"]


def _init_worker(threads: int, cache_dir: str | None) -> None:
    if cache_dir:
        os.environ["NUMBA_CACHE_DIR"] = cache_dir
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))  # type: ignore[attr-defined]


def spawn_pool(workers: int, cores: int | None = None) -> ProcessPoolExecutor:
    """``workers`` spawned processes, each with ``cores // workers`` numba threads and this
    process's numba cache."""
    cores = cores or os.cpu_count() or 1
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_worker,
        initargs=(max(1, cores // workers), os.environ.get("NUMBA_CACHE_DIR")),
    )


class ProcessRunner:
    """A pool of ``workers`` spawned processes; numba threads divided among them."""

    def __init__(self, workers: int, cores: int | None = None) -> None:
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = workers
        self._pool = spawn_pool(workers, cores)

    def map(self, fn: Callable[[TileUnit], UnitResult], units: list[TileUnit]) -> list[UnitResult]:
        return list(self._pool.map(fn, units))

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ProcessRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
