"""Units of work on dask.distributed (docs/scale-out.md): the same bits in this process, on a
LocalCluster and on an external cluster; a worker killed at random instants mid-job; a unit
that keeps killing workers; cancel; a service stopped or killed leaves no process behind;
/healthz without workers. Real clusters: LocalCluster, ``dask scheduler``, ``dask worker``."""

from __future__ import annotations

import io
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import dask
import httpx
import numpy as np
import psutil
import pytest
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
from rangefuse.engine.synth import make_dataset
from rangefuse.service._malloc import TUNABLES
from rangefuse.service.cluster import Cluster, RunInterruptedError
from rangefuse.service.jobs import JobRunner, JobsElsewhere, new_id
from rangefuse.service.queue import JobQueue
from rangefuse.service.settings import Settings
from rangefuse.storage import Store, open_store

from tests.test_service import Server

H = 0.04
PARAMS = FusionParams(NoiseModel(eps=2 * H, rho=0.05))
GRID = GridSpec(H, 8, "mapping")
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def room():
    return make_dataset("room", views=6)


@pytest.fixture(scope="module")
def cluster():
    with Cluster(workers=2, memory_limit="2GiB") as local:
        yield local


def _fuse(path: Path, scans, runner=None, cache_mb: float = 1.0):
    """Fuse into a new store, remove one scan, and read back the grid and the mesh."""
    with open_store(path, GRID, PARAMS, cache_mb=cache_mb, runner=runner) as scene:
        for item in scans:
            scene.store_scan(*item)
        scene.integrate_pending(group_scans=3)
        scene.remove(scans[1][0])
        mesh, _ = scene.extract_mesh()
        return scene.to_dense(), mesh


def _same(a, b) -> None:
    (dense_a, mesh_a), (dense_b, mesh_b) = a, b
    np.testing.assert_array_equal(dense_a.first_voxel, dense_b.first_voxel)
    assert np.array_equal(dense_a.logodds, dense_b.logodds, equal_nan=True)
    for field in ("vertices", "faces", "inferred"):
        np.testing.assert_array_equal(getattr(mesh_a, field), getattr(mesh_b, field))


class ExternalCluster:
    """``dask scheduler`` and ``dask worker`` processes, as on a cluster."""

    def __init__(self, tmp: Path, workers: int) -> None:
        self.file = tmp / "scheduler.json"
        env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
        self.procs = [subprocess.Popen(
            [str(BIN / "dask"), "scheduler", "--port", "0", "--no-dashboard",
             "--scheduler-file", str(self.file)],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )]  # fmt: skip
        deadline = time.time() + 60
        while not self.file.exists() and time.time() < deadline:
            time.sleep(0.1)
        self.address = json.loads(self.file.read_text())["address"]
        for _ in range(workers):
            self.add_worker()

    def add_worker(self) -> None:
        self.procs.append(subprocess.Popen(
            [str(BIN / "dask"), "worker", self.address, "--nthreads", "1", "--no-dashboard",
             "--preload", "rangefuse.service.worker"],
            env={**os.environ, "NUMBA_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        ))  # fmt: skip

    def close(self) -> None:
        for proc in reversed(self.procs):
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def _wait_for_workers(cluster: Cluster, n: int, timeout: float = 60.0) -> None:
    deadline = time.time() + timeout
    while cluster.n_workers() < n:
        assert time.time() < deadline, f"{cluster.n_workers()} of {n} workers"
        time.sleep(0.2)


def _engine_loaded() -> bool:
    return "rangefuse.storage.units" in sys.modules and "numba" in sys.modules


def test_the_cluster_processes_load_the_engine_before_the_first_unit(cluster):
    """The scheduler unpickles each graph (importing what its units name) and a worker's
    first unit loaded numba: both happen at start, not under the first job. The workers
    get glibc's malloc thresholds for multi-megabyte buffers."""
    _wait_for_workers(cluster, 2)
    assert cluster.client.run_on_scheduler(_engine_loaded)
    assert list(cluster.client.run(_engine_loaded).values()) == [True, True]
    tunables = set(cluster.client.run(lambda: os.environ.get("GLIBC_TUNABLES")).values())
    assert tunables == {TUNABLES}


def test_a_local_cluster_closes_at_once_even_while_its_workers_start():
    """The workers stop before the scheduler: stopped together, a worker spent its closing
    retrying the scheduler, 8 s a stop, and a worker still starting outlived a minute (and
    was killed). A bound on a hang, not a timing: a close takes about a second here."""
    cluster = Cluster(workers=2)
    procs = [psutil.Process(p.pid) for p in cluster._local._procs]  # type: ignore[union-attr]
    time.sleep(0.5)  # the workers are starting
    t0 = time.perf_counter()
    cluster.close()
    took = time.perf_counter() - t0
    assert took < 15.0, f"closing took {took:.1f} s"
    assert not [p for p in procs if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    codes = [p.returncode for p in cluster._local._procs]  # type: ignore[union-attr]
    assert -signal.SIGKILL not in codes, codes  # none needed killing


def test_in_process_local_and_external_clusters_give_the_same_bits(tmp_path, room, cluster):
    here = _fuse(tmp_path / "here", room.scans)
    _same(_fuse(tmp_path / "local", room.scans, cluster.runner()), here)
    external = ExternalCluster(tmp_path, workers=2)
    try:
        with Cluster(scheduler=external.address) as joined:
            _wait_for_workers(joined, 2)
            _same(_fuse(tmp_path / "external", room.scans, joined.runner()), here)
    finally:
        external.close()


@pytest.mark.slow
def test_a_worker_killed_at_random_instants_mid_job_changes_nothing(tmp_path, room, cluster):
    """kill -9 of a worker while a job runs: it is replaced, its units run again, and the
    scene ends with the same bits, 10 times out of 10. The kill comes at a random instant,
    or at the first moment after it when a worker runs a unit (most kills are mid-unit)."""
    expected = _fuse(tmp_path / "expected", room.scans, cache_mb=64)
    t0 = time.perf_counter()
    _fuse(tmp_path / "timing", room.scans, cluster.runner(), cache_mb=64)
    job_s = time.perf_counter() - t0
    rng = random.Random(3)
    mid_unit = 0  # kills of a worker that was running a unit
    for trial in range(10):
        result: list = []
        job = threading.Thread(
            target=lambda out=result, t=trial: out.append(
                _fuse(tmp_path / f"trial{t}", room.scans, cluster.runner(), cache_mb=64)
            )
        )
        job.start()
        time.sleep(rng.uniform(0.1, 0.8) * job_s)
        busy = _busy_workers(cluster, job, job_s)
        pids = cluster.client.run(os.getpid)
        victim = rng.choice(sorted(busy or pids))
        os.kill(pids[victim], signal.SIGKILL)
        mid_unit += victim in busy
        job.join(timeout=600)
        assert result, f"trial {trial} did not finish"
        _same(result[0], expected)
        _wait_for_workers(cluster, 1)  # its nanny restarts it, usually within 2 s
    assert mid_unit >= 5, mid_unit


def _busy_workers(cluster, job: threading.Thread, patience_s: float) -> set:
    """The workers running a unit now, or at the first moment one does within ``patience_s``
    while ``job`` runs (between two units none is: a kill there is not mid-unit); empty when
    none did."""
    deadline = time.perf_counter() + patience_s
    while True:
        busy = {addr for addr, tasks in cluster.client.processing().items() if tasks}
        if busy or not job.is_alive() or time.perf_counter() > deadline:
            return busy
        time.sleep(0.01)


def _job_runner(data_dir: Path, **settings) -> JobRunner:
    runner = JobRunner(data_dir, Settings(data_dir=data_dir, poll_s=0.05, **settings))
    runner.start()
    return runner


def _wait_for_jobs(queue: JobQueue, ids: list[str], timeout: float = 300.0) -> dict:
    deadline = time.time() + timeout
    while True:
        jobs = {j: queue.job(j) for j in ids}
        if all(job.state in ("done", "failed", "cancelled") for job in jobs.values()):
            return jobs
        assert time.time() < deadline, {j: job.state for j, job in jobs.items()}
        time.sleep(0.1)


def _scene_with(store: Store, scans, grid: GridSpec) -> str:
    scene_id = new_id()
    store.create_scene(scene_id, grid, PARAMS)
    for item in scans:
        store.store_scan(scene_id, *item)
    return scene_id


@pytest.mark.slow
def test_a_unit_that_keeps_killing_workers_fails_its_job_alone(tmp_path, room):
    """A scene whose units need more memory than a worker may use: its job fails, naming
    the scans and the limit, after a bounded number of tries; the next job completes."""
    data_dir = tmp_path / "data"
    with (
        Store.open(data_dir, create=True) as store,
        JobQueue(store.catalog.path) as queue,
        dask.config.set({"distributed.scheduler.allowed-failures": 1}),
    ):
        poisoned = _scene_with(store, room.scans[:2], GridSpec(0.005, 16, "mapping"))
        sane = _scene_with(store, room.scans, GRID)
        ids = [queue.create_job(new_id(), "t", s, "integrate", {}).id for s in (poisoned, sane)]
        runner = _job_runner(data_dir, workers=1, worker_memory="600MB", cache_mb=4000.0)
        try:
            jobs = _wait_for_jobs(queue, ids)
        finally:
            runner.stop()
        failed, done = jobs[ids[0]], jobs[ids[1]]
        assert failed.state == "failed", failed
        assert room.scans[0][0] in failed.error and "died 2 times" in failed.error
        assert "memory limit, 600MB" in failed.error
        assert done.state == "done", done
        with open_store(data_dir, scene_id=sane) as scene:
            expected = Volume(GRID, PARAMS)
            expected.add_many(room.scans)
            got, want = scene.to_dense(), expected.to_dense()
            assert np.array_equal(got.logodds, want.logodds, equal_nan=True)


@pytest.mark.parametrize("where", ["here", "elsewhere"])
def test_cancel_stops_a_running_job_and_leaves_the_store_consistent(tmp_path, where):
    """Cancelled in the runner's process, or by another HTTP process of the service (only
    the queue records it: the runner notices within poll_s)."""
    data = make_dataset("room", views=24)
    data_dir = tmp_path / "data"
    with Store.open(data_dir, create=True) as store, JobQueue(store.catalog.path) as queue:
        scene_id = _scene_with(store, data.scans, GridSpec(0.02, 16, "mapping"))
        job = queue.create_job(new_id(), "t", scene_id, "integrate", {})
        runner = _job_runner(data_dir, workers=2)
        try:
            deadline = time.time() + 120
            while queue.job(job.id).state != "running":
                assert time.time() < deadline
                time.sleep(0.05)
            time.sleep(1.0)
            jobs = runner if where == "here" else JobsElsewhere(queue)
            assert jobs.cancel(job.id, queue).state == "cancelling"
            (final,) = _wait_for_jobs(queue, [job.id]).values()
            assert final.state == "cancelled" and final.finished_at is not None
            queued = queue.create_job(new_id(), "t", "nope", "integrate", {})
            assert runner.cancel(queued.id, queue).state == "cancelled"  # queued: at once
            # what the cancelled job committed stays; the rest fuses as if never interrupted
            again = queue.create_job(new_id(), "t", scene_id, "integrate", {})
            assert _wait_for_jobs(queue, [again.id])[again.id].state == "done"
        finally:
            runner.stop()
    with open_store(data_dir, scene_id=scene_id) as scene:
        expected = Volume(GridSpec(0.02, 16, "mapping"), PARAMS)
        expected.add_many(data.scans)
        got, want = scene.to_dense(), expected.to_dense()
        assert np.array_equal(got.logodds, want.logodds, equal_nan=True)


def test_an_interrupted_runner_returns_once_its_running_units_have_ended(tmp_path, cluster):
    """Dask's cancel does not stop a task that runs: the runner waits for its running units
    to end, so that nothing of a stopped job writes under the scene's next job (a deletion
    found ``staging/`` recreated by a straggler after it removed the scene's folder)."""
    _wait_for_workers(cluster, 2)
    marks = tmp_path / "ended"
    marks.mkdir()

    def unit(i: int) -> int:
        import time as t

        t.sleep(2.0)
        (marks / str(i)).write_text("ended")
        return i

    stop = threading.Event()
    threading.Timer(0.5, stop.set).start()
    with pytest.raises(RunInterruptedError):
        cluster.runner(stop.is_set).map(unit, list(range(8)))
    ended = sorted(p.name for p in marks.iterdir())
    assert ended, "the runner returned while its units still ran"
    time.sleep(2.5)
    assert sorted(p.name for p in marks.iterdir()) == ended  # and none began after


def _descendants(pid: int) -> list[int]:
    try:
        return [p.pid for p in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _alive(pids: list[int]) -> list[int]:
    return [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"]


def _busy_server(tmp_path: Path) -> tuple[Server, str, list[int]]:
    """A server with a long job running (a reconstruction); its worker processes."""
    data = make_dataset("room", views=30)
    server = Server(tmp_path / "data").start()
    server.token = server.read_token()
    headers = {"Authorization": f"Bearer {server.token}"}
    scene = httpx.post(f"{server.url}/v1/scenes", headers=headers,
                       json={"name": "busy", "voxel_size": 0.02}).json()  # fmt: skip
    sensor = data.sensor.to_dict()
    for _, scan in data.scans:
        buf = io.BytesIO()
        np.save(buf, scan.range_m)
        meta = json.dumps({"pose": scan.T_W_S.tolist(), "sensor": sensor})
        answer = httpx.post(
            f"{server.url}/v1/scenes/{scene['id']}/scans",
            headers=headers,
            files={"range": ("r.npy", buf.getvalue()), "meta": (None, meta)},
        )
        assert answer.status_code == 202, answer.text
    # a reconstruction: fuses what is pending, then meshes the whole room (several seconds)
    job_id = httpx.post(f"{server.url}/v1/scenes/{scene['id']}/reconstructions",
                        headers=headers).json()["job"]["id"]  # fmt: skip
    deadline = time.time() + 120
    while httpx.get(f"{server.url}/v1/jobs/{job_id}", headers=headers).json()["state"] != "running":
        assert time.time() < deadline
        time.sleep(0.1)
    time.sleep(0.5)
    assert server.proc is not None
    workers = _descendants(server.proc.pid)
    assert len(workers) >= 2, workers  # the LocalCluster's worker processes
    return server, job_id, workers


@pytest.mark.slow
def test_sigterm_requeues_running_jobs_and_leaves_no_process(tmp_path):
    server, job_id, workers = _busy_server(tmp_path)
    assert server.proc is not None
    server.proc.send_signal(signal.SIGTERM)
    server.proc.wait(timeout=120)
    time.sleep(2.0)
    assert _alive(workers) == []
    with Store.open(server.data_dir) as store, JobQueue(store.catalog.path) as queue:
        assert queue.job(job_id).state == "queued"  # runs again at the next start


@pytest.mark.slow
def test_a_killed_service_leaves_no_worker(tmp_path):
    server, _, workers = _busy_server(tmp_path)
    assert server.proc is not None
    os.kill(server.proc.pid, signal.SIGKILL)  # the API process alone
    server.proc.wait(timeout=30)
    deadline = time.time() + 10
    while _alive(workers) and time.time() < deadline:
        time.sleep(0.2)
    assert _alive(workers) == []


def test_healthz_answers_503_while_no_worker_can_run_jobs(tmp_path):
    from fastapi.testclient import TestClient
    from rangefuse.service.app import create_app

    external = ExternalCluster(tmp_path, workers=0)
    try:
        app = create_app(Settings(data_dir=tmp_path / "data", scheduler=external.address))
        with TestClient(app) as client:
            answer = client.get("/healthz")
            assert answer.status_code == 503
            assert answer.json() == {"status": "no worker can run jobs", "workers": 0}
            external.add_worker()
            deadline = time.time() + 60
            while client.get("/healthz").status_code != 200:
                assert time.time() < deadline
                time.sleep(0.2)
            assert client.get("/healthz").json() == {"status": "ok", "workers": 1}
    finally:
        external.close()
