"""Idempotency keys with meaning: bound to the tenant, the scene and the SHA-256 of the
upload's parts; reused for another scan or scene they answer 422 and store nothing; they
expire after ``RANGEFUSE_IDEMPOTENCY_TTL_S``; stores of the previous version are migrated.

The accounts against a real SQLite file, and the upload route through a real ``rangefuse
serve`` on loopback.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from rangefuse.service.accounts import (
    Accounts,
    IdempotencyKeyReusedError,
    hash_token,
    upload_digest,
)
from rangefuse.service.app import create_app
from rangefuse.service.settings import Settings
from rangefuse.storage import Store

from tests.test_service import (
    ROOT,
    _meta,
    _n_scans,
    _npy,
    _scene_body,
    _upload,
    client_of,
    serving,
)

TTL_S = 4.0  # the test server's RANGEFUSE_IDEMPOTENCY_TTL_S

#: The service's tables as the previous version created them (before roles and bound keys).
_PREVIOUS_SCHEMA = """
CREATE TABLE IF NOT EXISTS tokens(
    hash TEXT PRIMARY KEY, tenant TEXT NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS idempotency(
    tenant TEXT NOT NULL, key TEXT NOT NULL, response TEXT NOT NULL,
    PRIMARY KEY(tenant, key));
"""


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    with Store.open(tmp_path / "store", create=True) as store:
        return store.catalog.path


# --- the accounts' tables ---------------------------------------------------------------------


def test_a_store_of_the_previous_version_opens_with_its_tokens_and_keys(db_path: Path) -> None:
    old = {"scan": {"id": "s-old", "name": "a", "state": "stored"}, "job": {"id": "j-old"}}
    with sqlite3.connect(db_path) as db:
        db.executescript(_PREVIOUS_SCHEMA)
        db.execute("INSERT INTO tokens VALUES(?,?,?)", (hash_token("old-token"), "alice", 1.0))
        db.execute("INSERT INTO idempotency VALUES(?,?,?)", ("alice", "k-old", json.dumps(old)))
    before = time.time()
    with Accounts(db_path, idempotency_ttl_s=0.5) as accounts:
        assert accounts.tenant("old-token") == "alice"
        assert accounts.caller("old-token").role == "tenant"
        # a key recorded before keys were bound answers as it did (its scene and body are
        # unknown), until one TTL after the migration
        assert accounts.recorded_response("alice", "k-old", "any-scene", "any-digest") == old
        accounts.remember_response("alice", "k-new", {"scan": {}}, "scene-1", "d1")
        with pytest.raises(IdempotencyKeyReusedError):
            accounts.recorded_response("alice", "k-new", "scene-2", "d1")
    with sqlite3.connect(db_path) as db:
        columns = {row[1] for row in db.execute("PRAGMA table_info(idempotency)")}
        assert {"scene_id", "body_sha256", "created_at"} <= columns
        (stamped,) = db.execute("SELECT created_at FROM idempotency WHERE key='k-old'").fetchone()
        assert before <= stamped <= time.time()
    # opening again migrates nothing twice; the service opens the store
    with Accounts(db_path) as accounts:
        assert accounts.n_tokens() == 1
    create_app(Settings(data_dir=db_path.parent))
    time.sleep(0.6)
    with Accounts(db_path, idempotency_ttl_s=0.5) as accounts:
        assert accounts.idempotent_response("alice", "k-old") is None  # expired


def test_a_key_is_bound_to_its_scene_and_body(db_path: Path) -> None:
    response = {"scan": {"id": "s1"}, "job": {"id": "j1"}}
    with Accounts(db_path) as accounts:
        assert accounts.recorded_response("alice", "k", "scene-1", "d1") is None
        accounts.remember_response("alice", "k", response, "scene-1", "d1")
        assert accounts.recorded_response("alice", "k", "scene-1", "d1") == response
        assert accounts.recorded_response("bob", "k", "scene-2", "d2") is None  # per tenant
        with pytest.raises(IdempotencyKeyReusedError) as other_scene:
            accounts.recorded_response("alice", "k", "scene-2", "d1")
        assert str(other_scene.value) == (
            "Idempotency-Key: 'k' is taken: it was first used in scene 'scene-1', not "
            "'scene-2'; nothing was stored. A retry must send the same scan to the same "
            "scene; a new scan needs a new key"
        )
        with pytest.raises(IdempotencyKeyReusedError, match="for another scan") as other_body:
            accounts.recorded_response("alice", "k", "scene-1", "d2")
        assert "scene" not in str(other_body.value).split("is taken:")[1].split(";")[0]
        with pytest.raises(IdempotencyKeyReusedError, match="scene 'scene-1'.*another scan"):
            accounts.recorded_response("alice", "k", "scene-2", "d2")


def test_keys_expire_and_can_be_used_again(db_path: Path) -> None:
    with Accounts(db_path, idempotency_ttl_s=0.3) as accounts:
        accounts.remember_response("alice", "k", {"first": 1}, "scene-1", "d1")
        time.sleep(0.4)
        assert accounts.recorded_response("alice", "k", "scene-2", "d2") is None
        accounts.remember_response("alice", "k", {"second": 2}, "scene-2", "d2")
        assert accounts.recorded_response("alice", "k", "scene-2", "d2") == {"second": 2}
    with sqlite3.connect(db_path) as db:
        assert db.execute("SELECT COUNT(*) FROM idempotency").fetchone() == (1,)


def test_the_digest_covers_both_parts_and_where_they_split() -> None:
    assert upload_digest(b"ab", b"c") != upload_digest(b"a", b"bc")
    assert upload_digest(b"ab", b"c") == upload_digest(b"ab", b"c")
    assert len(upload_digest(b"", b"")) == 64


# --- through the service ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(
        tmp_path_factory.mktemp("data"), RANGEFUSE_IDEMPOTENCY_TTL_S=str(TTL_S),
        RANGEFUSE_WORKERS="1",
    )  # fmt: skip


@pytest.fixture(scope="module")
def client(server):
    with client_of(server) as c:
        yield c


@pytest.fixture(scope="module")
def scans():
    from rangefuse.engine.synth import make_dataset

    data = make_dataset("object", views=2)
    return data, [(_npy(scan.range_m), _meta(scan)) for _, scan in data.scans]


def _scene(client, data) -> str:
    r = client.post("/v1/scenes", json=_scene_body(data))
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _stored_keys(server) -> list[tuple]:
    with Store.open(server.data_dir) as store, sqlite3.connect(store.catalog.path) as db:
        return db.execute(
            "SELECT tenant, key, scene_id, body_sha256, response FROM idempotency ORDER BY key"
        ).fetchall()


def test_a_retry_gets_the_first_answer(client, scans):
    data, parts = scans
    sid = _scene(client, data)
    first = _upload(client, sid, *parts[0], {"Idempotency-Key": "retry-1"})
    assert first.status_code == 202, first.text
    # httpx picks a new multipart boundary for each request; the file name is not hashed
    again = _upload(client, sid, *parts[0], {"Idempotency-Key": "retry-1"}, filename="b.npy")
    assert again.status_code == 202 and again.json() == first.json()
    assert _n_scans(client, sid) == 1


def test_the_same_key_with_another_scan_is_422_and_stores_nothing(server, client, scans):
    data, parts = scans
    sid = _scene(client, data)
    first = _upload(client, sid, *parts[0], {"Idempotency-Key": "body-1"})
    assert first.status_code == 202
    keys = _stored_keys(server)
    other = _upload(client, sid, *parts[1], {"Idempotency-Key": "body-1"})
    assert other.status_code == 422
    assert other.json()["detail"] == (
        "Idempotency-Key: 'body-1' is taken: it was first used for another scan (the range or "
        "meta part differs); nothing was stored. A retry must send the same scan to the same "
        "scene; a new scan needs a new key"
    )
    assert _n_scans(client, sid) == 1 and _stored_keys(server) == keys
    # the first scan's retry still gets its answer; other clients are served
    assert _upload(client, sid, *parts[0], {"Idempotency-Key": "body-1"}).json() == first.json()
    assert _upload(client, sid, *parts[1], {"Idempotency-Key": "body-2"}).status_code == 202
    assert _n_scans(client, sid) == 2
    assert client.get("/healthz").status_code == 200


def test_the_same_key_in_another_scene_is_422_and_stores_nothing(server, client, scans):
    data, parts = scans
    first_scene, second_scene = _scene(client, data), _scene(client, data)
    assert (
        _upload(client, first_scene, *parts[0], {"Idempotency-Key": "scene-1"}).status_code == 202
    )
    keys = _stored_keys(server)
    moved = _upload(client, second_scene, *parts[0], {"Idempotency-Key": "scene-1"})
    assert moved.status_code == 422
    assert moved.json()["detail"].startswith(
        f"Idempotency-Key: 'scene-1' is taken: it was first used in scene {first_scene!r}, "
        f"not {second_scene!r}; nothing was stored."
    )
    assert _n_scans(client, second_scene) == 0 and _stored_keys(server) == keys
    assert (
        _upload(client, second_scene, *parts[0], {"Idempotency-Key": "scene-2"}).status_code == 202
    )
    assert _n_scans(client, second_scene) == 1


def test_tenants_keep_separate_keys(server, client, scans):
    data, parts = scans
    made = subprocess.run(
        [sys.executable, "-m", "rangefuse.service.cli", "token", "create", "--tenant", "dora",
         "--data-dir", str(server.data_dir)],
        cwd=ROOT, capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    dora = {"Authorization": f"Bearer {made.stdout.strip()}"}
    mine = _scene(client, data)
    assert _upload(client, mine, *parts[0], {"Idempotency-Key": "shared"}).status_code == 202
    with httpx.Client(base_url=server.url, headers=dora, timeout=60) as other:
        theirs = _scene(other, data)
        r = _upload(other, theirs, *parts[1], {"Idempotency-Key": "shared"})
        assert r.status_code == 202, r.text
        assert _n_scans(other, theirs) == 1


def test_an_expired_key_can_be_used_for_a_new_scan(client, scans):
    data, parts = scans
    sid = _scene(client, data)
    first = _upload(client, sid, *parts[0], {"Idempotency-Key": "expires"})
    assert first.status_code == 202
    refused = _upload(client, sid, *parts[1], {"Idempotency-Key": "expires"})
    assert refused.status_code == 422
    time.sleep(TTL_S + 0.5)
    later = _upload(client, sid, *parts[1], {"Idempotency-Key": "expires"})
    assert later.status_code == 202, later.text
    assert later.json()["scan"]["id"] != first.json()["scan"]["id"]
    assert _n_scans(client, sid) == 2
