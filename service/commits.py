"""Group commit of uploads: the scans that arrive together are made durable together.

An upload is acknowledged (202) once its scan is archived with fsync and recorded in the
catalog. Done one upload at a time, each pays its own round of fsyncs, its own catalog and
queue transactions, and waits for every upload before it. Each request stages its scan in
the archive itself, in its own thread (:meth:`storage.Store.stage_scan`: checksum,
compression and writes, side by side with the other requests); the :class:`UploadCommitter`
thread takes every staged upload waiting when it is free and commits them as one batch
(:meth:`storage.Store.commit_scans`: one round of fsyncs, one catalog transaction), queues
one ``integrate`` job per scene, records the idempotency keys, and then answers them all.
A request waits on its future without holding a thread of the pool. An upload that is not
committed (a retry of a recorded key, an error) has its staged file removed.

Idempotency keys are checked here, in the committer's one thread: a retry that arrives in
the same batch as its first use waits for the next batch, and then gets the first answer.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rangefuse.storage import Store
from rangefuse.storage.store import PendingScan

from .accounts import Accounts
from .jobs import new_id
from .queue import JobQueue

__all__ = ["UploadCommitter"]

log = logging.getLogger("rangefuse.commits")

#: Most uploads stored as one batch.
MAX_BATCH = 64


@dataclass
class _Upload:
    scene_id: str
    tenant: str
    key: str | None
    digest: str | None
    pending: PendingScan
    future: Future[dict[str, Any]] = field(default_factory=Future)


class UploadCommitter:
    """The thread that stores uploads in batches (see the module's note)."""

    def __init__(self, data_dir: Path, accounts: Accounts) -> None:
        self.data_dir = Path(data_dir)
        self.accounts = accounts
        self._waiting: deque[_Upload] = deque()
        self._ready = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._loop, name="rangefuse-commits", daemon=True)
        #: Batches stored and uploads in them (for the logs and the benchmark).
        self.batches = 0
        self.uploads = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Store what is waiting, then stop."""
        with self._ready:
            self._stopping = True
            self._ready.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=60)

    def submit(
        self,
        scene_id: str,
        tenant: str,
        key: str | None,
        digest: str | None,
        pending: PendingScan,
    ) -> Future[dict[str, Any]]:
        """Queue an upload staged by the request (:meth:`Store.stage_scan`); the future
        answers its response (or raises what refused it)."""
        upload = _Upload(scene_id, tenant, key, digest, pending)
        with self._ready:
            if self._stopping:
                Store.discard_scans([pending])
                raise RuntimeError("the service is stopping")
            self._waiting.append(upload)
            self._ready.notify()
        return upload.future

    def _take(self) -> list[_Upload]:
        with self._ready:
            while not self._waiting and not self._stopping:
                self._ready.wait()
            batch: list[_Upload] = []
            while self._waiting and len(batch) < MAX_BATCH:
                batch.append(self._waiting.popleft())
            return batch

    def _loop(self) -> None:
        with Store.open(self.data_dir) as store, JobQueue(store.catalog.path) as queue:
            while True:
                batch = self._take()
                if not batch:
                    return  # stopping, nothing left
                try:
                    later = self._commit(store, queue, batch)
                except BaseException as exc:  # every upload of the batch learns why
                    for upload in batch:
                        if not upload.future.done():
                            Store.discard_scans([upload.pending])
                            upload.future.set_exception(exc)
                    if not isinstance(exc, Exception):
                        raise
                    log.warning("storing %d uploads failed: %s", len(batch), exc)
                    continue
                with self._ready:
                    self._waiting.extendleft(reversed(later))

    def _commit(self, store: Store, queue: JobQueue, batch: list[_Upload]) -> list[_Upload]:
        """Store one batch and answer it; returns the uploads left for the next batch."""
        todo: list[_Upload] = []
        later: list[_Upload] = []
        keys: set[tuple[str, str]] = set()
        for upload in batch:
            if upload.key is not None and upload.digest is not None:
                if (upload.tenant, upload.key) in keys:
                    later.append(upload)  # a retry of an upload of this batch: answered next
                    continue
                keys.add((upload.tenant, upload.key))
                try:
                    seen = self.accounts.recorded_response(
                        upload.tenant, upload.key, upload.scene_id, upload.digest
                    )
                except Exception as exc:  # the key was bound to another scan or scene
                    Store.discard_scans([upload.pending])
                    upload.future.set_exception(exc)
                    continue
                if seen is not None:  # a retry: its staged copy is dropped
                    Store.discard_scans([upload.pending])
                    upload.future.set_result(seen)
                    continue
            todo.append(upload)
        if not todo:
            return later
        rows = store.commit_scans([u.pending for u in todo])
        jobs: dict[str, str] = {}
        for upload, row in zip(todo, rows, strict=True):
            if isinstance(row, Exception):
                upload.future.set_exception(row)
                continue
            if upload.scene_id not in jobs:
                job = queue.queued_job(upload.scene_id, "integrate")
                if job is None:
                    job = queue.create_job(
                        new_id(), upload.tenant, upload.scene_id, "integrate", {}
                    )
                jobs[upload.scene_id] = job.id
            scan = {"id": row.id, "name": row.name, "state": row.state,
                    "far_ranges": upload.pending.far_ranges}  # fmt: skip
            response = {"scan": scan, "job": {"id": jobs[upload.scene_id]}}
            if upload.key is not None:
                self.accounts.remember_response(
                    upload.tenant, upload.key, response, upload.scene_id, upload.digest
                )
            upload.future.set_result(response)
        self.batches += 1
        self.uploads += len(todo)
        return later


def _integrate_job(queue: JobQueue, tenant: str, scene_id: str) -> str:
    """The scene's queued ``integrate`` job, or a new one (the scans are stored already, so
    a job that starts now fuses them)."""
    job = queue.queued_job(scene_id, "integrate")
    if job is None:
        job = queue.create_job(new_id(), tenant, scene_id, "integrate", {})
    return job.id
