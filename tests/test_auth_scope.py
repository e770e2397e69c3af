"""Secrets and scope: tenant and admin tokens, ``rangefuse token list|revoke``, no token in
any log, and the page's token kept out of URLs the server sees.

A real ``rangefuse serve`` on loopback (tests/test_service.py's ``Server``), a real store, the
real command line against the same store, and headless Chromium for the page.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import time

import httpx
import pytest
from rangefuse.storage import Store

from tests.test_offline_docs import CHROMIUM, Browser
from tests.test_service import ROOT, _scene_body, serving

SCENE = {"name": "desk", "voxel_size": 0.05, "mode": "mapping"}


def _cli(*args: str, data_dir) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rangefuse.service.cli", "token", *args, "--data-dir",
         str(data_dir)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _n_scenes(data_dir) -> int:
    with Store.open(data_dir) as store:
        return len(store.catalog.scenes())


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # no job runs here: one worker is enough
    yield from serving(tmp_path_factory.mktemp("data"), RANGEFUSE_WORKERS="1")


@pytest.fixture(scope="module")
def admin(server) -> str:
    return server.read_token("admin")


def _answer(server, path: str, headers: dict | None = None, method: str = "GET", **kw):
    return httpx.request(method, server.url + path, headers=headers or {}, timeout=30, **kw)


# --- roles ------------------------------------------------------------------------------------


def test_first_start_prints_a_tenant_token_and_an_admin_token(server, admin):
    printed = "".join(server.lines)
    assert f"created a token for tenant 'default': {server.token}" in printed
    assert f"admin token (for /metrics; no scenes): {admin}" in printed
    assert server.token != admin
    listed = _cli("list", data_dir=server.data_dir)
    assert listed.returncode == 0, listed.stderr
    rows = [line.split() for line in listed.stdout.splitlines()[1:3]]
    assert [(r[1], r[2]) for r in rows] == [("default", "tenant"), ("admin", "admin")]


def test_metrics_is_for_admin_tokens_only(server, admin):
    none = _answer(server, "/metrics")
    assert none.status_code == 401 and "missing bearer token" in none.json()["detail"]
    tenant = _answer(server, "/metrics", _bearer(server.token))
    assert tenant.status_code == 403
    assert tenant.json()["detail"] == (
        "needs an admin token (rangefuse token create --tenant NAME --admin); this is a token "
        "of tenant 'default'"
    )
    ok = _answer(server, "/metrics", _bearer(admin))
    assert ok.status_code == 200 and 'rangefuse_jobs{state="queued"}' in ok.text
    # liveness stays open
    assert _answer(server, "/healthz").status_code == 200


def test_admin_tokens_have_no_scenes(server, admin):
    before = _n_scenes(server.data_dir)
    made = _answer(server, "/v1/scenes", _bearer(admin), "POST", json=SCENE)
    assert made.status_code == 403
    assert made.json()["detail"].startswith("admin token: admin tokens read /metrics and have no")
    assert _answer(server, "/v1/jobs", _bearer(admin)).status_code == 403
    assert _n_scenes(server.data_dir) == before  # nothing stored
    assert _answer(server, "/v1/scenes", _bearer(server.token)).status_code == 200


# --- token list and revoke ------------------------------------------------------------------


def test_token_list_shows_ids_never_tokens(server, admin):
    made = _cli("create", "--tenant", "carol", data_dir=server.data_dir)
    assert made.returncode == 0, made.stderr
    carol = made.stdout.strip()
    listed = _cli("list", data_dir=server.data_dir)
    assert listed.returncode == 0
    assert listed.stdout.splitlines()[0].split() == ["id", "tenant", "role", "created", "(UTC)"]
    assert "carol" in listed.stdout
    for token in (server.token, admin, carol):
        assert token not in listed.stdout and token not in listed.stderr
    ids = [line.split()[0] for line in listed.stdout.splitlines()[1:]]
    assert all(len(i) == 12 and int(i, 16) >= 0 for i in ids)


def test_a_revoked_token_is_refused_at_once(server):
    made = _cli("create", "--tenant", "bob", data_dir=server.data_dir)
    bob = made.stdout.strip()
    assert _answer(server, "/v1/scenes", _bearer(bob)).status_code == 200
    bob_id = next(
        line.split()[0]
        for line in _cli("list", data_dir=server.data_dir).stdout.splitlines()
        if line.split()[1] == "bob"
    )
    revoked = _cli("revoke", bob_id, data_dir=server.data_dir)
    assert revoked.returncode == 0, revoked.stderr
    assert revoked.stdout.strip() == f"revoked token {bob_id} (tenant token of 'bob')"
    refused = _answer(server, "/v1/scenes", _bearer(bob))
    assert refused.status_code == 401
    assert refused.json()["detail"] == "invalid token (unknown or revoked)"
    assert "bob" not in _cli("list", data_dir=server.data_dir).stdout
    # the others keep working
    assert _answer(server, "/v1/scenes", _bearer(server.token)).status_code == 200


def test_revoke_refuses_unknown_short_and_ambiguous_ids(tmp_path):
    data_dir = tmp_path / "store"
    assert _cli("create", "--tenant", "a", data_dir=data_dir).returncode == 0
    with Store.open(data_dir) as store:
        db_path = store.catalog.path
    # two tokens whose hashes share a prefix (a real collision of 6 hex digits needs
    # thousands of tokens): rows written as the service writes them
    with sqlite3.connect(db_path) as db:
        for digest in ("abcdef01" + "0" * 56, "abcdef02" + "0" * 56):
            db.execute(
                "INSERT INTO tokens(hash, tenant, created_at, role) VALUES(?,?,?,?)",
                (digest, "twin", time.time(), "tenant"),
            )
    cases = {
        "abcdef": "token id: 'abcdef' names 2 tokens; give more characters",
        "123456": "token id: no token '123456' (see `rangefuse token list`)",
        "xyz": "token id: 'xyz' is not an id; give at least 6 hex characters",
    }
    for token_id, message in cases.items():
        out = _cli("revoke", token_id, data_dir=data_dir)
        assert out.returncode == 2, (token_id, out.stdout, out.stderr)
        assert f"rangefuse token: error: {message}" in out.stderr, (token_id, out.stderr)

    def tenants() -> list[str]:
        with sqlite3.connect(db_path) as db:
            return sorted(t for (t,) in db.execute("SELECT tenant FROM tokens"))

    assert tenants() == ["a", "twin", "twin"]  # nothing was revoked
    assert _cli("revoke", "abcdef01", data_dir=data_dir).returncode == 0
    assert tenants() == ["a", "twin"]


def test_token_create_refuses_an_empty_tenant(tmp_path):
    out = _cli("create", "--tenant", " ", data_dir=tmp_path / "store")
    assert out.returncode == 2
    assert "--tenant: must be 1 to 200 printable characters, got ' '" in out.stderr


# --- no token in any log ----------------------------------------------------------------------


def test_access_log_never_shows_query_strings(server):
    secret = "secret-in-a-query-7f3a"
    assert _answer(server, f"/?token={secret}").status_code == 200
    assert _answer(server, f"/v1/scenes?token={secret}").status_code == 401
    assert _answer(server, f"/docs?token={secret}&x=1").status_code == 200
    deadline = time.time() + 30
    while time.time() < deadline and not any(
        '"GET /docs HTTP/1.1" 200' in line for line in server.lines
    ):
        time.sleep(0.05)
    log = "".join(server.lines)
    assert '"GET / HTTP/1.1" 200' in log and '"GET /v1/scenes HTTP/1.1" 401' in log
    assert '"GET /docs HTTP/1.1" 200' in log
    assert secret not in log
    assert "?token=" not in log
    # a tenant's own bearer token is never logged either (only the first-start line has it)
    assert log.count(server.token) == 1


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (.ci/run installs it)")
def test_the_page_takes_the_token_from_the_fragment_and_keeps_it_out_of_urls(server):
    from rangefuse.engine.synth import make_dataset

    with httpx.Client(base_url=server.url, headers=_bearer(server.token), timeout=60) as c:
        body = _scene_body(make_dataset("object", views=1), name="fragment-scene")
        sid = c.post("/v1/scenes", json=body).json()["id"]
    n_log_lines = len(server.lines)
    browser = Browser(offline=True)
    try:
        browser.open(f"{server.url}/?scene={sid}#token={server.token}")
        browser.wait_for("document.body.innerText.includes('fragment-scene')")
        assert browser.evaluate("location.href") == f"{server.url}/?scene={sid}"
        assert browser.evaluate("sessionStorage.getItem('rangefuse-token')") == server.token
        assert browser.evaluate("localStorage.getItem('rangefuse-token')") is None
        # an old ?token= link is not read (the page asks for a token) and is dropped
        browser.evaluate("sessionStorage.clear()")
        browser.open(f"{server.url}/?token={server.token}&scene={sid}")
        browser.wait_for("document.readyState === 'complete'")
        assert browser.evaluate("location.href") == f"{server.url}/?scene={sid}"
        assert browser.evaluate("sessionStorage.getItem('rangefuse-token')") is None
        assert "fragment-scene" not in browser.evaluate("document.body.innerText")
        # the form: typing a token stores it for this tab and lists the scenes
        browser.evaluate(
            f"const i = document.getElementById('token'); i.value = {server.token!r};"
            "i.dispatchEvent(new Event('change'))"
        )
        browser.wait_for("document.body.innerText.includes('fragment-scene')")
        assert browser.evaluate("sessionStorage.getItem('rangefuse-token')") == server.token
    finally:
        browser.close()
    time.sleep(0.5)  # the last access log lines
    assert server.token not in "".join(server.lines[n_log_lines:])
