"""The job queue: jobs with their state, progress, message and result, and the meshes they
made.

The API process queues jobs; the dispatcher claims them, one running job per scene, and
worker processes record progress and outcome (:mod:`service.jobs`). A reconstruction job
records its mesh file in the ``meshes`` table (the latest per scene), which
``GET /v1/scenes/{id}/mesh`` serves. Both tables live in the store's SQLite file
(:mod:`service._database`), so a job survives a restart of the service.

A running job's ``message`` says what it waits on, for people (a worker compiling kernels,
:mod:`service.worker`); it is cleared when the job leaves ``running``.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._database import Database

__all__ = ["JOB_STATES", "JobQueue", "JobRow"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs(
    id TEXT PRIMARY KEY, seq INTEGER NOT NULL, tenant TEXT NOT NULL, scene_id TEXT,
    kind TEXT NOT NULL, state TEXT NOT NULL, progress REAL NOT NULL, error TEXT,
    payload TEXT NOT NULL, result TEXT, created_at REAL NOT NULL, finished_at REAL,
    message TEXT);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state, seq);
CREATE TABLE IF NOT EXISTS meshes(
    scene_id TEXT PRIMARY KEY, job_id TEXT NOT NULL, path TEXT NOT NULL, etag TEXT NOT NULL,
    faces INTEGER NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS runner(name TEXT PRIMARY KEY, value INTEGER NOT NULL);
"""

#: States of a job: ``cancelling`` is a running job asked to stop; the last three are final.
JOB_STATES = ("queued", "running", "cancelling", "done", "failed", "cancelled")
_FINAL = ("done", "failed", "cancelled")


@dataclass(frozen=True)
class JobRow:
    id: str
    tenant: str
    scene_id: str | None
    kind: str
    state: str
    progress: float
    error: str | None
    payload: dict[str, Any]
    result: dict[str, Any] | None
    created_at: float
    finished_at: float | None
    message: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The job as the API shows it (``message``, ``error``, ``finished_at`` and
        ``result`` only when set)."""
        out: dict[str, Any] = {
            "id": self.id,
            "kind": self.kind,
            "scene_id": self.scene_id,
            "state": self.state,
            "progress": self.progress,
            "created_at": self.created_at,
        }
        if self.message is not None:
            out["message"] = self.message
        if self.error is not None:
            out["error"] = self.error
        if self.finished_at is not None:
            out["finished_at"] = self.finished_at
        if self.result is not None:
            out["result"] = self.result
        return out


_COLUMNS = (
    "id, tenant, scene_id, kind, state, progress, error, payload, result, created_at, "
    "finished_at, message"
)


def _job_row(r: tuple[Any, ...]) -> JobRow:
    return JobRow(
        r[0], r[1], r[2], r[3], r[4], r[5], r[6], json.loads(r[7]),
        None if r[8] is None else json.loads(r[8]), r[9], r[10], r[11],
    )  # fmt: skip


def _add_message_column(db: Database) -> None:
    """Stores written before jobs had a ``message`` get the column (empty)."""
    if any(r[1] == "message" for r in db.rows("PRAGMA table_info(jobs)")):
        return
    try:
        db.run("ALTER TABLE jobs ADD COLUMN message TEXT")
    except sqlite3.OperationalError as exc:  # another process added it meanwhile
        if "duplicate column" not in str(exc):
            raise


class JobQueue:
    """The jobs and meshes tables in the SQLite file at ``path`` (the store's catalog file)."""

    def __init__(self, path: Path) -> None:
        self._db = Database(path, _SCHEMA)
        _add_message_column(self._db)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> JobQueue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- jobs ---------------------------------------------------------------------------------
    def create_job(
        self, job_id: str, tenant: str, scene_id: str | None, kind: str, payload: dict[str, Any]
    ) -> JobRow:
        with self._db.transaction():
            seq = int(self._db.rows("SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs")[0][0])
            self._db.run(
                "INSERT INTO jobs(id, seq, tenant, scene_id, kind, state, progress, payload,"
                " created_at) VALUES(?,?,?,?,?,'queued',0,?,?)",
                (job_id, seq, tenant, scene_id, kind, json.dumps(payload), time.time()),
            )
        job = self.job(job_id)
        assert job is not None
        return job

    def job(self, job_id: str) -> JobRow | None:
        rows = self._db.rows(f"SELECT {_COLUMNS} FROM jobs WHERE id=?", (job_id,))
        return _job_row(rows[0]) if rows else None

    def jobs(self, states: Sequence[str] | None = None, tenant: str | None = None) -> list[JobRow]:
        """Jobs in the order they were queued, optionally only those in ``states`` or of
        ``tenant``."""
        out = [_job_row(r) for r in self._db.rows(f"SELECT {_COLUMNS} FROM jobs ORDER BY seq")]
        return [
            j
            for j in out
            if (states is None or j.state in states) and (tenant is None or j.tenant == tenant)
        ]

    def queued_job(self, scene_id: str, kind: str) -> JobRow | None:
        """A queued job of this kind for the scene, if any (to fold new work into it)."""
        rows = self._db.rows(
            f"SELECT {_COLUMNS} FROM jobs WHERE scene_id=? AND kind=? AND state='queued' "
            "ORDER BY seq LIMIT 1",
            (scene_id, kind),
        )
        return _job_row(rows[0]) if rows else None

    def active_jobs(self, scene_id: str) -> list[JobRow]:
        """The scene's jobs that are queued, running or cancelling, oldest first."""
        rows = self._db.rows(
            f"SELECT {_COLUMNS} FROM jobs WHERE scene_id=? AND state IN "
            "('queued', 'running', 'cancelling') ORDER BY seq",
            (scene_id,),
        )
        return [_job_row(r) for r in rows]

    def deletion(self, scene_id: str) -> JobRow | None:
        """The scene's ``delete`` job that has not finished, if any: the scene is going."""
        return next((j for j in self.active_jobs(scene_id) if j.kind == "delete"), None)

    def deleting_scenes(self) -> set[str]:
        """Scenes with a ``delete`` job that has not finished."""
        rows = self._db.rows(
            "SELECT scene_id FROM jobs WHERE kind='delete' AND state IN "
            "('queued', 'running', 'cancelling')"
        )
        return {str(r[0]) for r in rows}

    def delete_job(self, job_id: str, tenant: str, scene_id: str) -> JobRow:
        """The scene's unfinished ``delete`` job, or a new one (``job_id``) queued now: one
        deletion per scene however many requests ask for it."""
        with self._db.transaction():
            found = self.deletion(scene_id)
            if found is not None:
                return found
            seq = int(self._db.rows("SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs")[0][0])
            self._db.run(
                "INSERT INTO jobs(id, seq, tenant, scene_id, kind, state, progress, payload,"
                " created_at) VALUES(?,?,?,?,'delete','queued',0,'{}',?)",
                (job_id, seq, tenant, scene_id, time.time()),
            )
        job = self.job(job_id)
        assert job is not None
        return job

    def claim_job(self, busy_scenes: Sequence[str]) -> JobRow | None:
        """The oldest queued job of a scene with no running job, now marked running."""
        # the runner asks every poll_s: without a queued job it takes no write lock (a
        # reader never waits on, nor holds up, the uploads' commits)
        if not self._db.rows("SELECT 1 FROM jobs WHERE state='queued' LIMIT 1"):
            return None
        with self._db.transaction():
            running = {
                r[0]
                for r in self._db.rows(
                    "SELECT scene_id FROM jobs WHERE state IN ('running', 'cancelling')"
                )
            }
            running |= set(busy_scenes)
            for r in self._db.rows(
                f"SELECT {_COLUMNS} FROM jobs WHERE state='queued' ORDER BY seq"
            ):
                job = _job_row(r)
                if job.scene_id in running:
                    continue
                self._db.run("UPDATE jobs SET state='running' WHERE id=?", (job.id,))
                return self.job(job.id)
        return None

    def update_job(
        self,
        job_id: str,
        *,
        state: str | None = None,
        progress: float | None = None,
        error: str | None = None,
        result: dict[str, Any] | None = None,
    ) -> None:
        sets: list[str] = []
        args: list[Any] = []
        if state is not None:
            if state not in JOB_STATES:
                raise ValueError(f"unknown job state {state!r}")
            sets.append("state=?")
            args.append(state)
            if state in _FINAL:
                sets.append("finished_at=?")
                args.append(time.time())
            if state in _FINAL or state == "queued":
                sets.append("message=NULL")
        if progress is not None:
            sets.append("progress=?")
            args.append(float(progress))
        if error is not None:
            sets.append("error=?")
            args.append(error)
        if result is not None:
            sets.append("result=?")
            args.append(json.dumps(result))
        if sets:
            self._db.run(f"UPDATE jobs SET {', '.join(sets)} WHERE id=?", (*args, job_id))

    def set_message(self, job_id: str, message: str | None) -> bool:
        """Say what a running job waits on (``None``: nothing); a job that is no longer
        running keeps none. Returns whether the job was running."""
        return bool(
            self._db.run(
                "UPDATE jobs SET message=? WHERE id=? AND state IN ('running', 'cancelling')",
                (message, job_id),
            )
        )

    def requeue_running(self) -> int:
        """Jobs a stopped process left running go back to the queue (restart); those it was
        asked to cancel are cancelled."""
        with self._db.transaction():
            self._db.run(
                "UPDATE jobs SET state='cancelled', finished_at=?, message=NULL "
                "WHERE state='cancelling'",
                (time.time(),),
            )
            return self._db.run(
                "UPDATE jobs SET state='queued', message=NULL WHERE state='running'"
            )

    def cancel(self, job_id: str) -> JobRow | None:
        """Cancel a job: a queued one is ``cancelled`` at once, a running one becomes
        ``cancelling`` (its runner stops it between two units); a finished one stays as it
        is. Returns the job as it is now."""
        with self._db.transaction():
            self._db.run(
                "UPDATE jobs SET state='cancelled', finished_at=?, message=NULL "
                "WHERE id=? AND state='queued'",
                (time.time(), job_id),
            )
            self._db.run("UPDATE jobs SET state='cancelling' WHERE id=? AND state='running'",
                         (job_id,))  # fmt: skip
        return self.job(job_id)

    def cancelling(self) -> list[str]:
        """Ids of the running jobs asked to stop (by any process of the service)."""
        return [str(r[0]) for r in self._db.rows("SELECT id FROM jobs WHERE state='cancelling'")]

    # --- the runner, as the processes that do not run it see it -------------------------------
    def set_workers(self, n: int) -> None:
        """Record how many workers the job runner has (0: jobs cannot make progress)."""
        self._db.run("INSERT OR REPLACE INTO runner(name, value) VALUES('workers', ?)", (n,))

    def workers(self) -> int:
        """The workers the job runner last recorded (0 before it has started)."""
        rows = self._db.rows("SELECT value FROM runner WHERE name='workers'")
        return int(rows[0][0]) if rows else 0

    def counts(self) -> dict[str, int]:
        """For metrics: the number of jobs in each state that has any."""
        return {
            str(state): int(n)
            for state, n in self._db.rows("SELECT state, COUNT(*) FROM jobs GROUP BY state")
        }

    # --- meshes -------------------------------------------------------------------------------
    def set_mesh(self, scene_id: str, job_id: str, path: str, etag: str, faces: int) -> None:
        """Record the mesh a reconstruction job wrote as the scene's latest."""
        self._db.run(
            "INSERT OR REPLACE INTO meshes(scene_id, job_id, path, etag, faces, created_at) "
            "VALUES(?,?,?,?,?,?)",
            (scene_id, job_id, path, etag, faces, time.time()),
        )

    def mesh(self, scene_id: str) -> tuple[str, str, int] | None:
        """``(path, etag, faces)`` of the scene's latest mesh, if any."""
        rows = self._db.rows("SELECT path, etag, faces FROM meshes WHERE scene_id=?", (scene_id,))
        return (str(rows[0][0]), str(rows[0][1]), int(rows[0][2])) if rows else None

    def forget_scene(self, scene_id: str) -> None:
        """Drop the mesh record of a deleted scene (its jobs stay, as history)."""
        self._db.run("DELETE FROM meshes WHERE scene_id=?", (scene_id,))
