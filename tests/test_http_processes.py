"""The service's other HTTP processes (``--http-processes``, :mod:`service.http_processes`):
a real ``rangefuse serve`` with two on loopback. The other process answers on the same port
(checked with the first one stopped, SIGSTOP: only the other can take the connection), its
uploads are stored and fused by the first one's jobs, its ``/healthz`` shows the workers the
first one recorded, its cancellations stop jobs, it is started again when it dies, and it
stops with the service.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager

import psutil
import pytest
from rangefuse.engine.synth import make_dataset

from tests.test_service import _meta, _npy, _scene_body, _upload, _wait, client_of, serving


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(
        tmp_path_factory.mktemp("data"), RANGEFUSE_HTTP_PROCESSES="2", RANGEFUSE_WORKERS="1"
    )


@pytest.fixture(scope="module")
def data():
    return make_dataset("object", views=2)


def _others(server) -> list[psutil.Process]:
    """The other HTTP processes of ``server`` (children of its process), living ones."""
    found = []
    for child in psutil.Process(server.proc.pid).children():
        try:
            if "rangefuse.service.http_processes" in " ".join(child.cmdline()):
                found.append(child)
        except psutil.Error:  # gone, or a zombie not yet reaped
            continue
    return found


@contextmanager
def _only_the_other_answers(server) -> Iterator[None]:
    """The first process stopped (SIGSTOP) meanwhile: a new connection can only be taken by
    the other process. Only while no job runs: stopped in a transaction, the first process
    would hold the catalog's write lock."""
    with client_of(server) as client:
        deadline = time.time() + 120
        while any(j["state"] in ("queued", "running") for j in client.get("/v1/jobs").json()):
            assert time.time() < deadline, "the jobs did not end"
            time.sleep(0.1)
    first = psutil.Process(server.proc.pid)
    first.suspend()
    try:
        yield
    finally:
        first.resume()


def test_the_other_process_takes_uploads_that_the_first_fuses(server, data):
    assert len(_others(server)) == 1
    with client_of(server, timeout=20) as client:
        sid = client.post("/v1/scenes", json=_scene_body(data)).json()["id"]
    with _only_the_other_answers(server), client_of(server, timeout=20) as other:
        health = other.get("/healthz")
        assert health.status_code == 200 and health.json()["workers"] == 1, health.text
        answers = [_upload(other, sid, _npy(s.range_m), _meta(s)) for _, s in data.scans]
        assert [r.status_code for r in answers] == [202, 202], [r.text for r in answers]
        job_id = answers[0].json()["job"]["id"]
        # the scans are on disk and queued; nobody fuses them while the first one is stopped
        assert other.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"
        assert len(other.get(f"/v1/scenes/{sid}/scans").json()) == 2
    with client_of(server) as client:
        assert _wait(client, job_id)["state"] == "done"
        scans = client.get(f"/v1/scenes/{sid}/scans").json()
        assert [s["state"] for s in scans] == ["fused", "fused"]


def test_a_cancellation_taken_by_the_other_process_is_carried_out(server, data):
    with client_of(server, timeout=20) as client:
        sid = client.post("/v1/scenes", json=_scene_body(data)).json()["id"]
        scan = data.scans[0][1]
        assert _upload(client, sid, _npy(scan.range_m), _meta(scan)).status_code == 202
        with _only_the_other_answers(server), client_of(server, timeout=20) as other:
            job = other.post(f"/v1/scenes/{sid}/reconstructions").json()["job"]
            cancelled = other.post(f"/v1/jobs/{job['id']}/cancel")
            assert cancelled.status_code == 202, cancelled.text
            assert cancelled.json()["state"] == "cancelled"  # queued: at once
        assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled"


def test_a_dead_http_process_is_started_again(server):
    (other,) = _others(server)
    os.kill(other.pid, signal.SIGKILL)
    deadline = time.time() + 60
    while True:
        again = [p for p in _others(server) if p.pid != other.pid and p.is_running()]
        if again:
            break
        assert time.time() < deadline, "no other HTTP process was started"
        time.sleep(0.2)
    # the connection waits in the socket's queue while the new process starts
    with _only_the_other_answers(server), client_of(server, timeout=60) as client:
        assert client.get("/healthz").status_code == 200


def test_the_other_processes_stop_with_the_service(tmp_path):
    gen = serving(tmp_path / "data", RANGEFUSE_HTTP_PROCESSES="3", RANGEFUSE_WORKERS="1")
    server = next(gen)
    others = _others(server)
    assert len(others) == 2
    gen.close()  # SIGINT to the first process; it stops the others (SIGTERM)
    assert server.proc.returncode == 130, "".join(server.lines[-30:])  # interrupted: SIGINT
    _, alive = psutil.wait_procs(others, timeout=30)
    assert not alive


def test_a_service_started_with_sigint_ignored_stops_on_sigint_as_interrupted(tmp_path):
    """A background job of a shell script (``rangefuse serve &``) starts with SIGINT ignored:
    SIGINT still stops the service, with the status of an interrupted command (it was 0)."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the child inherits it
    try:
        gen = serving(tmp_path / "data", RANGEFUSE_WORKERS="1")
        server = next(gen)
    finally:
        signal.signal(signal.SIGINT, previous)
    gen.close()
    assert server.proc.returncode == 130, "".join(server.lines[-30:])
