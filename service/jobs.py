"""Jobs: persisted in the job queue, run in spawned worker processes, resumed after a restart.

The API process only queues jobs (:mod:`service.queue`). A :class:`Dispatcher` thread
claims queued jobs (one at a time per scene) and runs :func:`run_job` on a pool of worker
processes started with ``spawn``; each job opens its scene for writing (waiting for the
scene's writer lock), does the work and records the outcome. A service killed mid-job
leaves the job ``running``; the next start puts it back in the queue, and since fusion and
extraction are exact and idempotent the job completes with the same result.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
import uuid
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.storage import Store, open_scene

from .queue import JobQueue, JobRow
from .runners import spawn_pool

__all__ = ["Dispatcher", "new_id", "run_job"]

log = logging.getLogger("rangefuse.jobs")

KINDS = ("integrate", "remove", "reconstruct")


def new_id() -> str:
    return uuid.uuid4().hex[:16]


def _mesh_path(store: Store, scene_id: str, job_id: str) -> Path:
    return store.scene_path(scene_id) / "meshes" / f"{job_id}.npz"


def run_job(data_dir: str, job_id: str, cache_mb: float) -> dict[str, Any]:
    """Run one job to completion (in a worker process); returns its result."""
    from rangefuse.storage._files import atomic_write

    with Store.open(data_dir) as store, JobQueue(store.catalog.path) as queue:
        job = queue.job(job_id)
        if job is None or job.scene_id is None:
            return {}
        if store.catalog.scene(job.scene_id) is None:
            queue.update_job(job_id, state="failed", error="the scene was deleted")
            return {}
        t0 = time.perf_counter()
        try:
            with open_scene(store, job.scene_id, cache_mb, wait=True) as scene:

                def progress(done: int, total: int) -> None:
                    queue.update_job(job_id, progress=done / max(total, 1))

                result: dict[str, Any]
                if job.kind == "integrate":
                    report = scene.integrate_pending(progress=progress)
                    result = {"scans": report.scans, "voxel_updates": report.voxel_updates}
                elif job.kind == "remove":
                    scan_id = job.payload["scan_id"]
                    removed = scene.remove(scan_id) if scan_id in scene else None
                    result = {
                        "scan_id": scan_id,
                        "tiles": 0 if removed is None else removed.tiles_written,
                    }
                elif job.kind == "reconstruct":
                    if scene.scan_rows(("stored",)):
                        scene.integrate_pending()
                    mesh, counts = scene.extract_mesh(
                        refine=bool(job.payload.get("refine", True)),
                        bounds=job.payload.get("bounds"),
                    )
                    path = _mesh_path(store, job.scene_id, job_id)
                    arrays = {
                        "vertices": mesh.vertices,
                        "faces": mesh.faces,
                        "inferred": mesh.inferred,
                    }
                    digest = hashlib.sha256()
                    for value in arrays.values():
                        digest.update(np.ascontiguousarray(value).tobytes())
                    atomic_write(
                        path,
                        lambda fh: np.savez(
                            fh,
                            vertices=arrays["vertices"],
                            faces=arrays["faces"],
                            inferred=arrays["inferred"],
                        ),
                        fsync=True,
                    )
                    queue.set_mesh(
                        job.scene_id, job_id, str(path), digest.hexdigest()[:32], mesh.n_faces
                    )
                    result = {"faces": mesh.n_faces, "vertices": mesh.n_vertices, **counts}
                else:
                    raise ValueError(f"unknown job kind {job.kind!r}")
            result["seconds"] = time.perf_counter() - t0
            queue.update_job(job_id, state="done", progress=1.0, result=result)
            return result
        except Exception as exc:  # a job's failure is recorded, never raised into the pool
            log.exception("job %s failed", job_id)
            queue.update_job(job_id, state="failed", error=f"{type(exc).__name__}: {exc}")
            return {}


class Dispatcher:
    """Claims queued jobs and runs them on worker processes (one running job per scene)."""

    def __init__(self, data_dir: Path, workers: int, cache_mb: float, poll_s: float) -> None:
        self.data_dir = data_dir
        self.workers = workers
        self.cache_mb = cache_mb
        self.poll_s = poll_s
        self._pool = spawn_pool(workers)
        self._running: dict[Future[dict[str, Any]], JobRow] = {}
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="rangefuse-dispatcher", daemon=True)

    def start(self) -> None:
        with Store.open(self.data_dir) as store, JobQueue(store.catalog.path) as queue:
            resumed = queue.requeue_running()
        if resumed:
            log.info("resuming %d interrupted jobs", resumed)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=10)
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _loop(self) -> None:
        with Store.open(self.data_dir) as store:
            path = store.catalog.path
        queue = JobQueue(path)
        try:
            while not self._stop.is_set():
                for fut in [f for f in self._running if f.done()]:
                    job = self._running.pop(fut)
                    exc = fut.exception()
                    if exc is not None:  # the worker process died
                        queue.update_job(job.id, state="failed", error=f"worker failed: {exc}")
                while len(self._running) < self.workers:
                    busy = [j.scene_id for j in self._running.values() if j.scene_id]
                    claimed = queue.claim_job(busy)
                    if claimed is None:
                        break
                    fut = self._pool.submit(run_job, str(self.data_dir), claimed.id, self.cache_mb)
                    self._running[fut] = claimed
                self._wake.wait(self.poll_s)
                self._wake.clear()
        finally:
            queue.close()
