"""The service's own tables (tokens, idempotency keys, jobs, meshes) in the store's SQLite file.

They moved out of storage's catalog into ``service/accounts.py`` and ``service/queue.py``;
the file and the column layouts stayed, so a store written before still opens with its
tokens, jobs and meshes.
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest
from rangefuse.service.accounts import Accounts, hash_token
from rangefuse.service.queue import JobQueue
from rangefuse.storage import Store


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    with Store.open(tmp_path / "store", create=True) as store:
        return store.catalog.path


def test_tokens_and_idempotency_keys(db_path: Path) -> None:
    with Accounts(db_path) as accounts:
        assert accounts.n_tokens() == 0
        token = accounts.create_token("alice")
        assert accounts.tenant(token) == "alice"
        assert accounts.tenant(token + "x") is None
        assert accounts.n_tokens() == 1
        assert accounts.idempotent_response("alice", "k") is None
        accounts.remember_response("alice", "k", {"scan": {"id": "s1"}})
        accounts.remember_response("alice", "k", {"scan": {"id": "s2"}})  # the first stays
        assert accounts.idempotent_response("alice", "k") == {"scan": {"id": "s1"}}
        assert accounts.idempotent_response("bob", "k") is None
    # only the hash is stored
    with sqlite3.connect(db_path) as db:
        assert db.execute("SELECT hash FROM tokens").fetchall() == [(hash_token(token),)]


def test_job_lifecycle(db_path: Path) -> None:
    with JobQueue(db_path) as queue:
        a = queue.create_job("a", "alice", "scene1", "integrate", {})
        queue.create_job("b", "alice", "scene1", "reconstruct", {"refine": True})
        queue.create_job("c", "bob", "scene2", "remove", {"scan_id": "s"})
        assert a.to_dict() == {"id": "a", "kind": "integrate", "scene_id": "scene1",
                               "state": "queued", "progress": 0.0,
                               "created_at": a.created_at}  # fmt: skip
        assert queue.queued_job("scene1", "integrate") == a
        assert queue.queued_job("scene1", "remove") is None
        assert [j.id for j in queue.jobs(tenant="alice")] == ["a", "b"]
        # one running job per scene; busy scenes are skipped
        assert queue.claim_job(busy_scenes=["scene2"]).id == "a"
        assert queue.claim_job(busy_scenes=[]).id == "c"
        assert queue.claim_job(busy_scenes=[]) is None
        queue.update_job("a", progress=0.5)
        queue.update_job("a", state="done", progress=1.0, result={"scans": 1})
        done = queue.job("a")
        assert done is not None and done.state == "done" and done.finished_at is not None
        assert done.to_dict()["result"] == {"scans": 1}
        queue.update_job("c", state="failed", error="boom")
        assert queue.job("c").to_dict()["error"] == "boom"
        assert queue.counts() == {"queued": 1, "done": 1, "failed": 1}
        assert queue.claim_job([]).id == "b"
        assert queue.requeue_running() == 1
        assert queue.job("b").state == "queued"
        with pytest.raises(ValueError, match="unknown job state"):
            queue.update_job("b", state="lost")
        assert queue.job("nope") is None


def test_meshes(db_path: Path) -> None:
    with JobQueue(db_path) as queue:
        assert queue.mesh("scene1") is None
        queue.set_mesh("scene1", "job1", "/m/1.npz", "e1", 10)
        queue.set_mesh("scene1", "job2", "/m/2.npz", "e2", 20)  # the latest replaces
        assert queue.mesh("scene1") == ("/m/2.npz", "e2", 20)
        queue.forget_scene("scene1")
        assert queue.mesh("scene1") is None


def test_threads_create_jobs_concurrently(db_path: Path) -> None:
    with JobQueue(db_path) as queue:

        def create(n: int) -> None:
            for k in range(20):
                queue.create_job(f"{n}-{k}", "t", f"scene{n}", "integrate", {})

        threads = [threading.Thread(target=create, args=(n,)) for n in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        jobs = queue.jobs()
        assert len(jobs) == 80
        with sqlite3.connect(db_path) as db:
            seqs = [r[0] for r in db.execute("SELECT seq FROM jobs ORDER BY seq")]
        assert seqs == list(range(1, 81))


def test_a_store_written_before_the_move_keeps_its_rows(tmp_path: Path) -> None:
    """The catalog created these tables itself before; the same columns, the same rows."""
    path = tmp_path / "store"
    with Store.open(path, create=True) as store:
        db_path = store.catalog.path
    with sqlite3.connect(db_path) as db:  # the catalog's schema of the service tables, then
        db.executescript(
            """
            CREATE TABLE jobs(
                id TEXT PRIMARY KEY, seq INTEGER NOT NULL, tenant TEXT NOT NULL, scene_id TEXT,
                kind TEXT NOT NULL, state TEXT NOT NULL, progress REAL NOT NULL, error TEXT,
                payload TEXT NOT NULL, result TEXT, created_at REAL NOT NULL, finished_at REAL);
            CREATE INDEX jobs_state ON jobs(state, seq);
            CREATE TABLE tokens(
                hash TEXT PRIMARY KEY, tenant TEXT NOT NULL, created_at REAL NOT NULL);
            CREATE TABLE idempotency(
                tenant TEXT NOT NULL, key TEXT NOT NULL, response TEXT NOT NULL,
                PRIMARY KEY(tenant, key));
            CREATE TABLE meshes(
                scene_id TEXT PRIMARY KEY, job_id TEXT NOT NULL, path TEXT NOT NULL,
                etag TEXT NOT NULL, faces INTEGER NOT NULL, created_at REAL NOT NULL);
            """
        )
        db.execute("INSERT INTO tokens VALUES(?, 'old', 1.0)", (hash_token("secret"),))
        db.execute("INSERT INTO idempotency VALUES('old', 'k', '{\"job\": {\"id\": \"j\"}}')")
        db.execute(
            "INSERT INTO jobs VALUES('j', 1, 'old', 's', 'reconstruct', 'running', 0.5, NULL,"
            " '{}', NULL, 1.0, NULL)"
        )
        db.execute("INSERT INTO meshes VALUES('s', 'j', '/m.npz', 'e', 7, 1.0)")
    with Store.open(path) as store:  # storage opens it as before
        assert store.catalog.scenes() == []
    with Accounts(db_path) as accounts, JobQueue(db_path) as queue:
        assert accounts.tenant("secret") == "old"
        assert accounts.idempotent_response("old", "k") == {"job": {"id": "j"}}
        assert queue.requeue_running() == 1
        assert queue.job("j").state == "queued"
        assert queue.create_job("j2", "old", "s", "integrate", {}).id == "j2"
        assert [j.id for j in queue.jobs()] == ["j", "j2"]
        assert queue.mesh("s") == ("/m.npz", "e", 7)
