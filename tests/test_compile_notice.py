"""A job whose units wait on a worker compiling kernels says so (issue 20, "the first run is
silent"), and ``rangefuse serve`` says at start whether numba's cache is cold.

A real compilation by a real Dask worker of the job runner's own cluster: the unit compiles
a fresh kernel whose typing blocks until the test lets it go (a numba ``overload`` typing
function runs inside the compilation), so the job is seen waiting on it through the real
path: numba's compile event on the worker, the Dask event, the job runner, the jobs table
and the API's job model. No full compile of the engine: its kernels would take minutes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from numba import njit
from numba.extending import overload
from rangefuse.service.api.models import JobOut
from rangefuse.service.jobs import COMPILING_MESSAGE, JobRunner, _Compilations, new_id
from rangefuse.service.queue import JobQueue
from rangefuse.service.settings import Settings
from rangefuse.service.warmup import cache_state
from rangefuse.storage import Store

ROOT = Path(__file__).resolve().parents[1]

#: The file whose existence lets the held compilation finish (set on the worker by the unit).
_GO = ""


def _held() -> int:
    """Stands for a kernel that is slow to compile (typed by :func:`_type_held`)."""
    return 7


@overload(_held)
def _type_held():  # type: ignore[no-untyped-def]
    """Runs while numba compiles a kernel that calls ``_held``: waits for the go file."""
    deadline = time.monotonic() + 300
    while not os.path.exists(_GO) and time.monotonic() < deadline:
        time.sleep(0.05)
    return lambda: 7


def _unit_compiling_until(go: str) -> int:
    """A unit that compiles a fresh kernel, held open until ``go`` exists."""
    global _GO
    _GO = go

    @njit(cache=False)
    def kernel() -> int:
        return _held()

    return int(kernel())


def _wait_for(queue: JobQueue, job_id: str, message: str | None, timeout: float = 120.0):
    deadline = time.time() + timeout
    while True:
        job = queue.job(job_id)
        assert job is not None
        if job.message == message:
            return job
        assert time.time() < deadline, (job.state, job.message)
        time.sleep(0.05)


def test_a_worker_compiling_kernels_shows_on_the_job_until_it_is_done(tmp_path):
    data_dir = tmp_path / "data"
    go = tmp_path / "go"
    with Store.open(data_dir, create=True) as store, JobQueue(store.catalog.path) as queue:
        # a runner that claims no job (its loop starts at once and would race the test for
        # the job below; model_copy skips the validation that keeps jobs >= 1)
        settings = Settings(data_dir=data_dir, workers=1, poll_s=3600.0)
        runner = JobRunner(data_dir, settings.model_copy(update={"jobs": 0}))
        runner.start()
        try:
            job = queue.create_job(new_id(), "t", "scene", "integrate", {})
            assert queue.claim_job([]).id == job.id  # running, as a carried-out job is
            assert job.message is None and "message" not in JobOut.from_row(job).model_dump(
                exclude_unset=True
            )
            result: list[list[int]] = []
            units = runner.runner_for(job.id)
            thread = threading.Thread(
                target=lambda: result.append(units.map(_unit_compiling_until, [str(go)]))
            )
            thread.start()
            try:
                waiting = _wait_for(queue, job.id, COMPILING_MESSAGE)
                assert waiting.state == "running" and waiting.progress == 0.0
                shown = JobOut.from_row(waiting).model_dump(exclude_unset=True)
                assert shown["message"].startswith("compiling kernels, first run only")
                assert "rangefuse warmup" in shown["message"]
            finally:
                go.touch()
                thread.join(timeout=300)
            assert result == [[7]]
            assert _wait_for(queue, job.id, None).state == "running"  # compiled: no message
            # a late report of a job that ended changes nothing
            queue.update_job(job.id, state="done", progress=1.0)
            assert not queue.set_message(job.id, COMPILING_MESSAGE)
            assert queue.job(job.id).message is None
        finally:
            runner.stop()


def test_a_job_waits_while_any_of_its_workers_compiles():
    woken: list[int] = []
    seen = _Compilations(lambda: woken.append(1))
    seen.on_event((0.0, {"job": "j", "worker": "a", "compiling": True}))
    seen.on_event((0.0, {"job": "j", "worker": "b", "compiling": True}))
    seen.on_event((0.0, {"job": "k", "worker": "b", "compiling": True}))
    assert seen.changes() == {"j": True, "k": True}
    seen.on_event((0.0, {"job": "j", "worker": "a", "compiling": False}))
    assert seen.changes() == {}  # b still compiles for j
    seen.on_event((0.0, {"job": "j", "worker": "b", "compiling": False}))
    seen.on_event((0.0, {"job": "k", "worker": "b", "compiling": False}))
    seen.on_event((0.0, {"job": "k", "worker": "b", "compiling": True}))
    assert seen.changes() == {"j": False, "k": True}
    seen.forget("k")  # the job ended; its worker died mid-compilation
    seen.on_event((0.0, "not an event"))
    assert seen.changes() == {}
    assert len(woken) == 7


def test_the_message_lives_only_while_the_job_runs(tmp_path):
    with Store.open(tmp_path / "data", create=True) as store:
        path = store.catalog.path
    with JobQueue(path) as queue:
        queued = queue.create_job("q", "t", "s1", "integrate", {})
        assert not queue.set_message(queued.id, "x")  # queued: nothing to wait on yet
        running = queue.claim_job([])
        assert running is not None and queue.set_message(running.id, "x")
        assert queue.job(running.id).message == "x"
        queue.update_job(running.id, state="queued", progress=0.0)  # the service stops
        assert queue.job(running.id).message is None
        assert queue.claim_job([]).id == running.id and queue.set_message(running.id, "x")
        assert queue.requeue_running() == 1  # a restart after a kill
        assert queue.job(running.id).message is None
        assert queue.claim_job([]).id == running.id and queue.set_message(running.id, "x")
        queue.update_job(running.id, state="failed", error="boom")
        assert queue.job(running.id).message is None


def test_serve_says_when_the_kernel_cache_is_cold(tmp_path):
    from tests.test_service import Server

    cache = tmp_path / "numba"
    server = Server(tmp_path / "data", env={"NUMBA_CACHE_DIR": str(cache)}).start()
    try:
        server.read_token()
        (line,) = [line for line in server.lines if line.startswith("kernels: ")]
    finally:
        server.stop()
    assert f"numba's cache {cache} holds no compiled kernel of this rangefuse" in line
    assert "the first jobs compile the kernels they need" in line
    assert "`rangefuse warmup` compiles them all ahead of time" in line


def test_the_cache_state_counts_the_engine_kernels_it_holds(tmp_path, monkeypatch):
    cache = tmp_path / "numba"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    state = cache_state()
    assert state.cold and (state.fresh, state.stale) == (0, 0) and state.path == cache
    # compile one small engine kernel into the empty cache, in a process of its own
    compile_one = (
        "import rangefuse.service\n"
        "from rangefuse.engine.grid import _pack\n"
        "import numpy as np\n"
        "_pack(np.zeros((2, 3), np.int64), 1 << 20)\n"
    )
    subprocess.run(
        [sys.executable, "-c", compile_one],
        cwd=ROOT,
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache)},
        check=True,
    )
    state = cache_state()
    assert not state.cold and (state.fresh, state.stale) == (1, 0)
