"""Where units of work run: a Dask cluster, started on this machine or joined
(docs/scale-out.md).

:class:`Cluster` holds a ``dask.distributed`` client, on a local cluster it starts (a
scheduler process and worker processes, each supervised by a nanny, with a memory limit;
they die with this process: :class:`_LocalProcesses`) or on a running scheduler
(``tcp://HOST:PORT``). :class:`DaskRunner` runs a scene's units of work on it
(:class:`storage.units.Runner`): a worker that dies is replaced and its units run again,
which gives the same bits (docs/storage.md, "Units that can run again"); a unit that keeps
killing workers fails with a message that says which scans, and what the limit was; a
runner can be interrupted (a cancelled job, a stopping service).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import dask
from dask.utils import parse_bytes
from distributed import Client, Future, wait
from distributed.scheduler import KilledWorker
from rangefuse.storage._heap import libc
from rangefuse.storage.units import MeshUnit, PlanUnit, TileUnit

from ._malloc import with_tunables

__all__ = ["Cluster", "DaskRunner", "RunInterruptedError", "UnitFailedError"]

log = logging.getLogger("rangefuse.cluster")

Item = TypeVar("Item")
Result = TypeVar("Result")

#: How often a runner looks whether it was interrupted while its units run.
_POLL_S = 0.2
#: How often the slots ask the scheduler how many worker threads there are (a round trip
#: that returns every worker's state; the Dask client's IO loop took 13 % of the API
#: process's CPU under upload load when it was asked every 0.2 s).
_CAPACITY_S = 1.0
#: How long a runner that stops early (interrupted, or a unit failed) waits for its units
#: already running to end: Dask's cancel does not stop a running task, and one that goes on
#: would write its staged chunks under the scene's next job (a deletion removes the scene's
#: folder, then a straggler recreated ``staging/``).
_DRAIN_S = 60.0


class UnitFailedError(RuntimeError):
    """A unit of work killed every worker that ran it (the message says which scans)."""


class RunInterruptedError(Exception):
    """The runner was interrupted: its job was cancelled, or the service stops."""


def _scans(ids: Sequence[str]) -> str:
    shown = ", ".join(ids[:8]) + (" ..." if len(ids) > 8 else "")
    return f"scan {shown}" if len(ids) == 1 else f"scans {shown}"


def describe(unit: Any) -> str:
    """What a unit does, for people: ``scan scan_0007: fusing it``."""
    if isinstance(unit, TileUnit):
        ids = sorted({scan_id for scan_id, *_ in unit.steps})
        verb = "removing" if unit.steps and all(s[3] < 0 for s in unit.steps) else "fusing"
        return f"{_scans(ids)}: {verb} {'it' if len(ids) == 1 else 'them'}"
    if isinstance(unit, PlanUnit):
        ids = unit.scans or [s.scan_id for s in unit.spheres]
        return f"{_scans(ids) if ids else 'tiles'}: planning the {unit.kind}"
    if isinstance(unit, MeshUnit):
        return f"{len(unit.keys)} tiles: meshing them"
    return type(unit).__name__


class _Slots:
    """Units in flight on a cluster, at most one per worker thread, shared by the runners of
    one client (jobs that run side by side).

    Dask sends a worker more tasks than it has threads; when a worker dies, every task it
    held counts as a suspect, so a unit that kills workers would take the units of other
    jobs queued beside it down with it. Submitting a unit only when a thread is free keeps
    a worker's death on the unit that ran.
    """

    def __init__(self, client: Client) -> None:
        self.client = client
        self._lock = threading.Lock()
        self._in_flight = 0
        self._threads = 0
        self._asked = -math.inf

    def _capacity(self) -> int:
        now = time.monotonic()
        if now - self._asked > _CAPACITY_S:  # ask the scheduler at most every _CAPACITY_S
            try:
                workers = self.client.scheduler_info(n_workers=-1)["workers"].values()
                self._threads = sum(int(w.get("nthreads", 1)) for w in workers)
            except Exception:  # the scheduler went away: nothing can run
                self._threads = 0
            self._asked = now
        return self._threads

    def acquire(self) -> bool:
        """Take a slot when a worker thread is free; False when none is."""
        with self._lock:
            if self._in_flight >= self._capacity():
                return False
            self._in_flight += 1
            return True

    def release(self) -> None:
        with self._lock:
            self._in_flight -= 1


class DaskRunner:
    """Runs units on a Dask cluster (see the module's note).

    ``interrupted()`` is asked while units run; when it says yes, the runner submits no
    more, waits for the units already running to end (:meth:`_drain`) and raises
    :class:`RunInterruptedError` (what the units staged is dropped by the next run: nothing
    was committed).
    """

    def __init__(
        self,
        client: Client,
        memory_limit: str,
        interrupted: Callable[[], bool] | None = None,
        slots: _Slots | None = None,
    ) -> None:
        self.client = client
        self.memory_limit = memory_limit
        self.interrupted = interrupted or (lambda: False)
        self.slots = slots or _Slots(client)

    @property
    def workers(self) -> int:
        """Workers now (at least 1): how many parts a scene splits its tiles into."""
        return max(1, len(self.client.scheduler_info(n_workers=-1)["workers"]))

    def map(
        self,
        fn: Callable[[Item], Result],
        units: Sequence[Item],
        done: Callable[[int], None] | None = None,
    ) -> list[Result]:
        """Run ``fn`` on every unit (``done(i)`` as unit ``i`` finishes); each unit is
        submitted once a worker thread is free for it (:class:`_Slots`), so a worker holds the
        one unit it runs, and a worker's death is blamed on that unit alone."""
        results: dict[int, Result] = {}
        running: dict[Future, int] = {}
        waiting = list(range(len(units)))[::-1]
        try:
            while waiting or running:
                if self.interrupted():
                    raise RunInterruptedError("interrupted")
                while waiting and self.slots.acquire():
                    i = waiting.pop()
                    running[self.client.submit(fn, units[i], pure=False)] = i
                for future in self._first_done(list(running)):
                    i = running.pop(future)
                    self.slots.release()
                    if future.status == "error":
                        self._raise(units[i], future)
                    results[i] = future.result()
                    if done is not None:
                        done(i)
            return [results[i] for i in range(len(units))]
        finally:
            if running:
                self._drain(list(running))
                for _ in running:
                    self.slots.release()

    def _drain(self, futures: list[Future]) -> None:
        """Wait (at most :data:`_DRAIN_S`) for the units still running to end, then cancel
        what has not: the job that stops records its end only once nothing of it runs."""
        with contextlib.suppress(TimeoutError):
            wait(futures, timeout=_DRAIN_S)
        left = [f for f in futures if not f.done()]
        if left:
            log.warning("%d units still ran %.0f s after their job stopped", len(left), _DRAIN_S)
            self.client.cancel(left)

    @staticmethod
    def _first_done(futures: list[Future]) -> set[Future]:
        """The futures done after waiting at most ``_POLL_S`` for the first one."""
        if not futures:
            time.sleep(_POLL_S)  # no worker thread is free: wait for one
            return set()
        try:
            done, _ = wait(futures, timeout=_POLL_S, return_when="FIRST_COMPLETED")
        except TimeoutError:
            return set()
        return set(done)

    def _raise(self, unit: Any, future: Future) -> None:
        exc = future.exception()
        if isinstance(exc, KilledWorker):
            raise UnitFailedError(
                f"{describe(unit)}: the worker running it died {exc.allowed_failures + 1} "
                f"times (a worker is stopped when it uses more than its memory limit, "
                f"{self.memory_limit}); giving up"
            ) from None
        raise exc


class Cluster:
    """A Dask client: on ``workers`` local worker processes of ``memory_limit`` each, or on
    the scheduler at ``scheduler``. Close it when done (a local cluster's processes stop)."""

    def __init__(
        self,
        workers: int = 2,
        memory_limit: str = "auto",
        scheduler: str | None = None,
    ) -> None:
        self._local: _LocalProcesses | None = None
        if scheduler:
            self.client = Client(scheduler, timeout="30s")
            self.memory_limit = "set by the cluster's workers"
        else:
            if workers < 1:
                raise ValueError(f"workers: must be at least 1, got {workers}")
            self._local = _LocalProcesses(workers, _limit_bytes(memory_limit, workers))
            try:
                self.client = Client(self._local.address, timeout="30s")
            except BaseException:
                self._local.close()
                raise
            self.memory_limit = _limit_text(memory_limit, workers)
        self._slots = _Slots(self.client)

    def runner(self, interrupted: Callable[[], bool] | None = None) -> DaskRunner:
        return DaskRunner(self.client, self.memory_limit, interrupted, self._slots)

    def n_workers(self) -> int:
        """Workers that can run units now."""
        try:
            return len(self.client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # the scheduler went away
            return 0

    def close(self) -> None:
        self.client.close()
        if self._local is not None:
            self._local.close()

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: How much the local cluster's workers yield to the API process (``nice``): on a machine
#: they share, requests (an upload's 202 waits on the API process) go before fusion, which
#: is throughput work that catches up once uploads pause.
WORKER_NICE = 10

#: Dask settings of the local cluster's processes, unless the environment gives its own:
#: no statistical profiler in the workers (it samples the running unit every 10 ms, for a
#: dashboard the workers do not serve: a fifth to a quarter of their CPU under upload load)
#: and the event loops' health tick every second instead of 50 times a second. Idle, the
#: scheduler and two workers went from about 9.6% of a core to 3.9%.
QUIET_DASK = {
    "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
    "DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL": "1s",
}


class _LocalProcesses:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes (each under its nanny,
    which restarts it), children of this process.

    The scheduler runs in a process of its own, not in this one as a ``LocalCluster``'s
    does: under upload load its work (task transitions, messages, monitoring) took a fifth
    of the API process's CPU, and uploads went from 39-47 to 58-73 a second without it.
    The children are started by a thread that lives as long as they do, with
    ``PR_SET_PDEATHSIG``: when this process dies, even by kill -9, the kernel kills them (the
    signal follows the thread that forked them); a worker exits with its nanny.
    """

    def __init__(self, workers: int, memory_limit: int) -> None:
        self._folder = tempfile.TemporaryDirectory(prefix="rangefuse-cluster-")
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._procs: list[subprocess.Popen[bytes]] = []
        self._error: BaseException | None = None
        self.address = ""
        self._thread = threading.Thread(
            target=self._run, args=(workers, memory_limit), name="rangefuse-cluster",
            daemon=True,
        )  # fmt: skip
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self.close()
            raise RuntimeError(f"starting the local Dask cluster failed: {self._error}")

    def _spawn(self, args: list[str], env: dict[str, str], nice: int = 0) -> None:
        quiet = subprocess.DEVNULL
        proc = subprocess.Popen(
            [sys.executable, "-m", *args], env=env, stdin=quiet, stdout=quiet, stderr=quiet,
            preexec_fn=_die_with_parent if nice == 0 else partial(_die_with_parent, nice),
        )  # fmt: skip
        self._procs.append(proc)

    def _run(self, workers: int, memory_limit: int) -> None:
        try:
            file = Path(self._folder.name) / "scheduler.json"
            cores = os.cpu_count() or 1
            env = with_tunables(
                {**QUIET_DASK, **os.environ, "NUMBA_NUM_THREADS": str(max(1, cores // workers))}
            )
            # the scheduler gives up on a unit after this many dead workers (this process's
            # dask config, e.g. DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES)
            failures = dask.config.get("distributed.scheduler.allowed-failures")
            scheduler_env = {**env, "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": str(failures)}
            # the scheduler unpickles each graph's units, importing what they name: numba,
            # zarr and the engine took it 1.5 s of CPU on the first job, under that job's
            # uploads; preloaded, they load while the service starts
            self._spawn(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                         "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(file),
                         "--preload", "rangefuse.storage.units"],
                        scheduler_env)  # fmt: skip
            deadline = time.monotonic() + 60
            while not file.exists():
                if self._procs[0].poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the dask scheduler did not start")
                time.sleep(0.05)
            self.address = json.loads(file.read_text())["address"]
            for i in range(workers):
                self._spawn(["distributed.cli.dask_worker", self.address, "--nthreads", "1",
                             "--memory-limit", str(memory_limit), "--no-dashboard",
                             "--name", f"local-{i}", "--preload", "rangefuse.service.worker"],
                            env, WORKER_NICE)  # fmt: skip
        except BaseException as exc:
            self._error = exc
        finally:
            self._ready.set()
        self._stop.wait()  # the children's parent thread lives until close()

    def close(self) -> None:
        """Stop the workers, then the scheduler (SIGTERM; SIGKILL after 30 s). The scheduler
        goes last: a worker whose scheduler went away first spent its closing retrying it
        (8 s a stop, and over 60 s for a worker still starting, measured 2026-12-07)."""
        workers, scheduler = self._procs[1:], self._procs[:1]
        for group in (workers, scheduler):
            for proc in group:
                proc.terminate()
            for proc in group:
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        self._stop.set()
        self._folder.cleanup()


def _die_with_parent(nice: int = 0) -> None:
    """In a child before it runs: be killed when the thread that started it ends, and lower
    its priority by ``nice``. Only calls of functions resolved beforehand (no ``dlopen``
    between fork and exec)."""
    _PRCTL(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if nice:
        os.nice(nice)


_PR_SET_PDEATHSIG = 1
#: libc's prctl, resolved in the parent (Linux, the project's platform: without a C library
#: the import fails here).
_PRCTL = libc().prctl  # type: ignore[union-attr]


def _limit_bytes(memory_limit: str, workers: int) -> int:
    """Each worker's memory limit in bytes (``auto``: the machine's memory divided among
    them)."""
    if memory_limit == "auto":
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        return int(total / workers)
    return int(parse_bytes(memory_limit))


def _limit_text(memory_limit: str, workers: int) -> str:
    if memory_limit == "auto":
        try:
            total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError):
            return "the machine's memory divided among the workers"
        return f"{total / workers / 2**30:.1f} GiB"
    return str(memory_limit)
