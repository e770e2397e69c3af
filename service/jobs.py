"""Jobs: queued in the job queue, carried out here, their units of work on a Dask cluster.

The API process queues jobs (:mod:`service.queue`). A :class:`JobRunner` claims them, one
running job per scene, and carries each out in a thread of this process: it opens the
scene for writing (its lock, its catalog) and hands every unit of work, planning, fusion,
removal, rebuilds and meshing, to the cluster (:mod:`service.cluster`). Nothing heavy runs
in this process, and the catalog never leaves it.

- A worker that dies mid-unit is replaced and its units run again: the job completes with
  the same bits. A unit that keeps killing workers fails its job with a message that names
  its scans; the queue goes on.
- A job whose unit waits on a worker compiling kernels (a cold numba cache) says so in its
  ``message`` (:class:`_Compilations`; the workers report it, :mod:`service.worker`).
- ``cancel`` stops a job between units (nothing is committed; what was staged is dropped by
  the next run): the job reads ``cancelled``. A cancellation recorded in the queue by another
  process of the service (``settings.http_processes``) is noticed within ``poll_s``.
- Stopping the service (SIGTERM) interrupts the running jobs the same way and puts them back
  in the queue; a killed service leaves them ``running``, and the next start queues them
  again. Fusion and extraction are exact and can run again, so a resumed job gives the
  result an uninterrupted one would have.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
from rangefuse.storage import Store, open_scene
from rangefuse.storage._files import atomic_write
from rangefuse.storage.scene import Scene
from rangefuse.storage.units import Runner

from ._disk import DISK_FULL, is_disk_full
from .cluster import Cluster, RunInterruptedError, UnitFailedError
from .previews import make_preview
from .queue import JobQueue, JobRow
from .settings import Settings
from .warmup import COMPILING
from .worker import COMPILE_TOPIC, OnJob, load_kernels

__all__ = ["COMPILING_MESSAGE", "JobRunner", "Jobs", "JobsElsewhere", "new_id", "run_job"]

log = logging.getLogger("rangefuse.jobs")

KINDS = ("integrate", "remove", "reconstruct", "delete")

#: The error of a job stopped by a full disk.
_JOB_DISK_FULL = (
    "the store's disk is full: the job stopped (groups of scans it committed before stay "
    "fused; the others stay stored). Free space, then upload again or ask for a "
    "reconstruction to carry on"
)


#: A running job's ``message`` while a worker compiles kernels that its units need.
COMPILING_MESSAGE = (
    f"{COMPILING} (a worker compiles the kernels this job needs: up to 2 minutes; "
    "`rangefuse warmup` compiles them ahead of time)"
)

Item = TypeVar("Item")
Result = TypeVar("Result")


def new_id() -> str:
    return uuid.uuid4().hex[:16]


def run_job(
    store: Store, queue: JobQueue, job: JobRow, runner: Runner, cache_mb: float
) -> dict[str, Any]:
    """Carry out one job (its units on ``runner``); returns its result. Raises what stopped
    it: :class:`~service.cluster.RunInterruptedError`, :class:`~service.cluster.UnitFailedError` or
    the error of a unit."""
    assert job.scene_id is not None
    t0 = time.perf_counter()
    with open_scene(store, job.scene_id, cache_mb, runner, wait=True) as scene:

        def progress(lo: float, hi: float) -> Callable[[int, int], None]:
            """Reports ``done`` of ``total`` as the job's progress between ``lo`` and ``hi``."""
            return lambda done, total: queue.update_job(
                job.id, progress=lo + (hi - lo) * done / max(total, 1)
            )

        result: dict[str, Any]
        if job.kind == "integrate":
            report = scene.integrate_pending(progress=progress(0.0, 1.0))
            result = {"scans": report.scans, "voxel_updates": report.voxel_updates}
        elif job.kind == "remove":
            scan_id = job.payload["scan_id"]
            removed = scene.remove(scan_id) if scan_id in scene else None
            result = {"scan_id": scan_id, "tiles": 0 if removed is None else removed.tiles_written}
        elif job.kind == "reconstruct":
            result = _reconstruct(scene, queue, job, progress)
        else:
            raise ValueError(f"unknown job kind {job.kind!r}")
    result["seconds"] = time.perf_counter() - t0
    return result


def _reconstruct(
    scene: Scene,
    queue: JobQueue,
    job: JobRow,
    progress: Callable[[float, float], Callable[[int, int], None]],
) -> dict[str, Any]:
    """Fuse the scans still pending (the first half of the progress when there are any),
    mesh (up to 90%), save the mesh and its preview."""
    meshing_from = 0.0
    if scene.scan_rows(("stored",)):
        meshing_from = 0.5
        scene.integrate_pending(progress=progress(0.0, meshing_from))
    mesh, counts = scene.extract_mesh(
        refine=bool(job.payload.get("refine", True)),
        bounds=job.payload.get("bounds"),
        progress=progress(meshing_from, 0.9),
    )
    path = scene.store.scene_path(scene.scene_id) / "meshes" / f"{job.id}.npz"
    arrays = {"vertices": mesh.vertices, "faces": mesh.faces, "inferred": mesh.inferred}
    digest = hashlib.sha256()
    for value in arrays.values():
        digest.update(np.ascontiguousarray(value).tobytes())
    atomic_write(
        path,
        lambda fh: np.savez(
            fh, vertices=arrays["vertices"], faces=arrays["faces"], inferred=arrays["inferred"]
        ),
        fsync=True,
    )
    preview_faces = make_preview(scene.runner, path)  # for the web page (service/previews.py)
    queue.set_mesh(scene.scene_id, job.id, str(path), digest.hexdigest()[:32], mesh.n_faces)
    return {"faces": mesh.n_faces, "vertices": mesh.n_vertices, "preview_faces": preview_faces,
            **counts}  # fmt: skip


class _OnJobRunner:
    """A job's runner whose units report the compilations they cause as the job's
    (:class:`service.worker.OnJob`)."""

    def __init__(self, runner: Runner, job_id: str) -> None:
        self.runner = runner
        self.job_id = job_id

    @property
    def workers(self) -> int:
        return self.runner.workers

    def map(
        self,
        fn: Callable[[Item], Result],
        units: Sequence[Item],
        done: Callable[[int], None] | None = None,
    ) -> list[Result]:
        return self.runner.map(OnJob(fn, self.job_id), units, done)


class _Compilations:
    """Which jobs wait on a worker compiling kernels: fed with the workers' events
    (:data:`service.worker.COMPILE_TOPIC`, in the Dask client's thread); ``changes()`` hands
    the jobs whose answer changed to the thread that records them."""

    def __init__(self, changed: Callable[[], None]) -> None:
        self._lock = threading.Lock()
        self._workers: dict[str, set[str]] = {}  # job -> workers compiling for it
        self._changes: dict[str, bool] = {}
        self._changed = changed

    def on_event(self, event: tuple[float, Any]) -> None:
        """A worker's event ``(timestamp, {"job", "worker", "compiling"})``."""
        _, msg = event
        try:
            job_id, worker, compiling = str(msg["job"]), str(msg["worker"]), bool(msg["compiling"])
        except (TypeError, KeyError):
            log.warning("ignored a malformed compilation event: %r", msg)
            return
        with self._lock:
            workers = self._workers.setdefault(job_id, set())
            before = bool(workers)
            if compiling:
                workers.add(worker)
            else:
                workers.discard(worker)
            if bool(workers) != before:
                self._changes[job_id] = bool(workers)
            if not workers:
                del self._workers[job_id]
        self._changed()

    def changes(self) -> dict[str, bool]:
        """The jobs whose state changed since the last call: whether they wait now."""
        with self._lock:
            changes, self._changes = self._changes, {}
        return changes

    def forget(self, job_id: str) -> None:
        """The job ended (a worker that died mid-compilation never reports its end)."""
        with self._lock:
            self._workers.pop(job_id, None)
            self._changes.pop(job_id, None)


@dataclass
class _Running:
    thread: threading.Thread
    cancelled: threading.Event
    scene_id: str | None


class Jobs(Protocol):
    """The job runner as the routes use it: :class:`JobRunner` in the process that runs it,
    :class:`JobsElsewhere` in the service's other HTTP processes."""

    def start(self) -> None: ...
    def stop(self) -> None: ...
    def wake(self) -> None: ...
    def cancel(self, job_id: str, queue: JobQueue) -> JobRow | None: ...
    def workers(self) -> int: ...


class JobsElsewhere:
    """The job runner seen from an HTTP process that does not run it: the first process of
    the service runs it (:mod:`service.http_processes`) and looks at the queue every
    ``poll_s``, where it finds the jobs queued and the cancellations recorded here; the
    workers are those it last recorded."""

    def __init__(self, queue: JobQueue) -> None:
        self._queue = queue

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def wake(self) -> None:
        pass  # the runner looks every poll_s

    def cancel(self, job_id: str, queue: JobQueue) -> JobRow | None:
        return queue.cancel(job_id)

    def workers(self) -> int:
        return self._queue.workers()


#: How often the runner records its workers for the other HTTP processes (seconds).
_WORKERS_EVERY_S = 1.0


class JobRunner:
    """Claims queued jobs and carries them out (see the module's note)."""

    def __init__(self, data_dir: Path, settings: Settings) -> None:
        self.data_dir = Path(data_dir)
        self.settings = settings
        self.cluster: Cluster | None = None
        self._running: dict[str, _Running] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._compilations = _Compilations(self._wake.set)
        self._thread = threading.Thread(target=self._loop, name="rangefuse-jobs", daemon=True)
        self._runner_queue: JobQueue | None = None  # the runner's queue, opened by start()
        self._workers_seen: int | None = 0
        self._workers_asked = float("-inf")

    def _queue(self) -> JobQueue:
        with Store.open(self.data_dir) as store:
            return JobQueue(store.catalog.path)

    def start(self) -> None:
        """Put jobs a stopped service left running back in the queue, start or join the
        cluster, and begin claiming jobs."""
        self._runner_queue = self._queue()
        self._runner_queue.set_workers(0)  # none until the cluster's have joined
        resumed = self._runner_queue.requeue_running()
        if resumed:
            log.info("resuming %d interrupted jobs", resumed)
        load_kernels()  # numba's start, not under the first job while requests are served
        s = self.settings
        self.cluster = Cluster(s.workers, s.worker_memory, s.scheduler)
        self.cluster.client.subscribe_topic(COMPILE_TOPIC, self._compilations.on_event)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def runner_for(self, job_id: str, interrupted: Callable[[], bool] | None = None) -> Runner:
        """The runner of job ``job_id``'s units, on the cluster: a worker that compiles
        kernels for one of them shows on the job's ``message`` while it does."""
        assert self.cluster is not None
        return _OnJobRunner(self.cluster.runner(interrupted), job_id)

    def workers(self) -> int:
        """Workers that can run units now (0: jobs cannot make progress); a number that
        changed is recorded for the other HTTP processes."""
        n = 0 if self.cluster is None else self.cluster.n_workers()
        with self._lock:
            changed = self._workers_seen != n
            self._workers_seen = n
        if changed and self._runner_queue is not None:
            try:
                self._runner_queue.set_workers(n)
            except Exception as exc:  # a full disk: /healthz still answers; recorded later
                with self._lock:
                    self._workers_seen = None
                log.debug("recording the workers failed: %s", exc)
        return n

    def cancel(self, job_id: str, queue: JobQueue) -> JobRow | None:
        """Cancel a job: a queued one at once, a running one between two of its units."""
        job = queue.cancel(job_id)
        with self._lock:
            running = self._running.get(job_id)
        if running is not None:
            running.cancelled.set()
        return job

    def stop(self) -> None:
        """Interrupt the running jobs (they go back to the queue), then stop the cluster."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)
        with self._lock:
            threads = [r.thread for r in self._running.values()]
        for thread in threads:
            thread.join(timeout=60)
        if self.cluster is not None:
            self.cluster.close()
        if self._runner_queue is not None:
            self._runner_queue.close()

    def _loop(self) -> None:
        queue = self._runner_queue
        assert queue is not None  # start() opened it
        while not self._stop.is_set():
            try:
                self._show_compilations(queue)
                self._notice_cancellations(queue)
                self._record_workers()
                self._claim(queue)
            except Exception as exc:  # the catalog cannot be written (a full disk): later
                log.warning("claiming jobs failed, trying again: %s", exc)
                self._stop.wait(max(1.0, self.settings.poll_s))
            self._wake.wait(self.settings.poll_s)
            self._wake.clear()

    def _show_compilations(self, queue: JobQueue) -> None:
        """Record on each running job whether a worker compiles kernels for it now."""
        for job_id, compiling in self._compilations.changes().items():
            queue.set_message(job_id, COMPILING_MESSAGE if compiling else None)

    def _notice_cancellations(self, queue: JobQueue) -> None:
        """Stop the running jobs that another process of the service cancelled."""
        with self._lock:
            running = dict(self._running)
        if running:
            for job_id in queue.cancelling():
                if job_id in running:
                    running[job_id].cancelled.set()

    def _record_workers(self) -> None:
        """Keep the workers recorded for the other HTTP processes' ``/healthz`` (asking the
        scheduler at most every :data:`_WORKERS_EVERY_S`; :meth:`workers` records)."""
        now = time.monotonic()
        if now - self._workers_asked >= _WORKERS_EVERY_S:
            self._workers_asked = now
            self.workers()

    def _claim(self, queue: JobQueue) -> None:
        """Start queued jobs while fewer than ``settings.jobs`` run (one per scene)."""
        with self._lock:
            for job_id in [j for j, r in self._running.items() if not r.thread.is_alive()]:
                del self._running[job_id]
            scenes = [r.scene_id for r in self._running.values() if r.scene_id]
        while len(scenes) < self.settings.jobs and not self._stop.is_set():
            claimed = queue.claim_job(scenes)
            if claimed is None:
                break
            self._begin(claimed)
            scenes.append(claimed.scene_id or "")

    def _begin(self, job: JobRow) -> None:
        cancelled = threading.Event()
        thread = threading.Thread(
            target=self._carry_out, args=(job, cancelled), name=f"rangefuse-job-{job.id}",
            daemon=True,
        )  # fmt: skip
        with self._lock:
            self._running[job.id] = _Running(thread, cancelled, job.scene_id)
        thread.start()

    def _carry_out(self, job: JobRow, cancelled: threading.Event) -> None:
        runner = self.runner_for(job.id, lambda: cancelled.is_set() or self._stop.is_set())
        with Store.open(self.data_dir) as store, JobQueue(store.catalog.path) as queue:
            outcome = self._outcome(store, queue, job, runner, cancelled)
            self._compilations.forget(job.id)
            self._record(queue, job.id, outcome)  # clears the job's message

    def _outcome(
        self,
        store: Store,
        queue: JobQueue,
        job: JobRow,
        runner: Runner,
        cancelled: threading.Event,
    ) -> dict[str, Any]:
        """Carry out ``job``; returns how it ended, as ``update_job``'s arguments."""
        try:
            if job.kind == "delete":
                return self._delete(store, job)
            if job.scene_id is None or store.catalog.scene(job.scene_id) is None:
                return {"state": "failed", "error": "the scene was deleted"}
            result = run_job(store, queue, job, runner, self.settings.cache_mb)
        except RunInterruptedError:
            if cancelled.is_set():
                return {"state": "cancelled"}
            return {"state": "queued", "progress": 0.0}  # the service stops: runs again later
        except UnitFailedError as exc:
            return {"state": "failed", "error": str(exc)}
        except Exception as exc:  # a job's failure is recorded, never raised
            if is_disk_full(exc):
                log.warning("job %s: %s (%s)", job.id, DISK_FULL, exc)
                return {"state": "failed", "error": _JOB_DISK_FULL}
            log.exception("job %s failed", job.id)
            return {"state": "failed", "error": f"{type(exc).__name__}: {exc}"}
        return {"state": "done", "progress": 1.0, "result": result}

    def _record(self, queue: JobQueue, job_id: str, outcome: dict[str, Any]) -> None:
        """Record how a job ended; while the catalog cannot be written (a full disk), try
        again every second, so that the job never stays ``running`` behind a live runner.
        A service that stops meanwhile leaves it ``running``: the next start queues it."""
        while True:
            try:
                queue.update_job(job_id, **outcome)
                return
            except Exception as exc:
                log.warning("job %s: recording its end failed, trying again: %s", job_id, exc)
                if self._stop.wait(1.0):
                    return

    @staticmethod
    def _delete(store: Store, job: JobRow) -> dict[str, Any]:
        """A ``delete`` job: the scene's other jobs were cancelled when it was queued, and
        it runs once none of them runs (one job per scene); it waits here, never in a
        request, for a writer of another process to let go."""
        assert job.scene_id is not None
        t0 = time.perf_counter()
        if store.catalog.scene(job.scene_id) is not None:
            store.delete_scene(job.scene_id, wait=True)
        with JobQueue(store.catalog.path) as queue:
            queue.forget_scene(job.scene_id)
        result = {"scene_id": job.scene_id, "seconds": time.perf_counter() - t0}
        return {"state": "done", "progress": 1.0, "result": result}
