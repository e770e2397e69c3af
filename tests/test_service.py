"""The REST service, end to end: a real uvicorn on loopback, a real store, worker processes."""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from rangefuse.engine.synth import make_dataset
from rangefuse.service.cli import main
from rangefuse.storage import write_dataset
from rangefuse.storage.importers import encode_png

ROOT = Path(__file__).resolve().parents[1]
VOXEL = 0.04


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Server:
    """``rangefuse serve`` in a subprocess."""

    def __init__(
        self, data_dir: Path, max_upload_mb: float = 8.0, env: dict[str, str] | None = None
    ) -> None:
        self.data_dir = data_dir
        self.port = _free_port()
        self.max_upload_mb = max_upload_mb
        self.env = env or {}  # more RANGEFUSE_* settings
        self.token = ""
        self.proc: subprocess.Popen[str] | None = None
        self.lines: list[str] = []  # everything the server printed

    def start(self) -> Server:
        env = {
            **os.environ,
            "RANGEFUSE_MAX_UPLOAD_MB": str(self.max_upload_mb),
            "RANGEFUSE_POLL_S": "0.05",
            "PYTHONUNBUFFERED": "1",
            **self.env,
        }
        cmd = [
            sys.executable,
            "-m",
            "rangefuse.service.cli",
            "serve",
            "--data-dir",
            str(self.data_dir),
        ]
        self.proc = subprocess.Popen(
            [*cmd, "--port", str(self.port)],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # kill() takes the worker processes down too
        )
        # read the output as it comes: a server whose pipe is full blocks on its next log line
        threading.Thread(target=self._drain, args=(self.proc.stdout,), daemon=True).start()
        deadline = time.time() + 60
        while time.time() < deadline:
            assert self.proc.poll() is None, "".join(self.lines)
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                time.sleep(0.2)
        raise AssertionError("the server did not start")

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _drain(self, stream) -> None:
        for line in stream:
            self.lines.append(line)

    def read_token(self, role: str = "tenant") -> str:
        """The token the first start printed: tenant 'default''s, or with ``role="admin"``
        the admin token."""
        marker = "created a token" if role == "tenant" else "admin token"
        deadline = time.time() + 30
        while time.time() < deadline:
            for line in list(self.lines):
                if marker in line:
                    return line.rsplit(" ", 1)[1].strip()
            time.sleep(0.05)
        raise AssertionError("no token printed:\n" + "".join(self.lines))

    def kill(self) -> None:
        """kill -9 the server and its worker processes."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()


def serving(data_dir: Path, max_upload_mb: float = 8.0, **env: str) -> Iterator[Server]:
    """A started server with its first token (``env``: more ``RANGEFUSE_*`` settings),
    stopped afterwards: ``yield from`` it in a fixture."""
    srv = Server(data_dir, max_upload_mb, env).start()
    try:
        srv.token = srv.read_token()
        yield srv
    finally:
        srv.stop()


def client_of(server: Server, token: str | None = None, timeout: float = 60) -> httpx.Client:
    """An HTTP client of ``server`` with ``token`` (default: the server's first token)."""
    return httpx.Client(
        base_url=server.url,
        headers={"Authorization": f"Bearer {token or server.token}"},
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def client(server):
    with client_of(server) as c:
        yield c


@pytest.fixture(scope="module")
def object_data():
    return make_dataset("object", views=4)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _meta(scan, **extra) -> str:
    return json.dumps({"pose": scan.T_W_S.tolist(), "sensor": scan.sensor.to_dict(), **extra})


def _scene_body(data, **extra) -> dict:
    return {"name": "obj", "voxel_size": VOXEL, "mode": "closed", "bounds": list(data.bounds),
            "tile_size": 8, **extra}  # fmt: skip


def _upload(client, scene_id, range_bytes, meta, headers=None, filename="range.npy"):
    files = {"range": (filename, range_bytes), "meta": (None, meta)}
    return client.post(f"/v1/scenes/{scene_id}/scans", files=files, headers=headers or {})


def _wait(client, job_id, timeout=180.0) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("done", "failed"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish")


def _n_scans(client, scene_id) -> int:
    return len(client.get(f"/v1/scenes/{scene_id}/scans").json())


# --------------------------------------------------------------------------------------------


def test_end_to_end_matches_the_command_line(server, client, object_data, tmp_path):
    r = client.post("/v1/scenes", json=_scene_body(object_data))
    assert r.status_code == 201, r.text
    scene = r.json()
    assert scene["noise"] == {"eps": 2 * VOXEL, "eps_per_m": 0.0, "rho": 0.05,
                              "falloff": 2 * VOXEL, "shape": "linear"}  # fmt: skip
    assert scene["tile_size"] == 8 and scene["filter"] == "none"
    sid = scene["id"]
    jobs = set()
    for name, scan in object_data.scans:
        r = _upload(client, sid, _npy(scan.range_m), _meta(scan, name=name))
        assert r.status_code == 202, r.text
        body = r.json()
        assert body["scan"]["state"] == "stored" and body["scan"]["name"] == name
        jobs.add(body["job"]["id"])
    for job_id in jobs:
        assert _wait(client, job_id)["state"] == "done"
    assert {s["state"] for s in client.get(f"/v1/scenes/{sid}/scans").json()} == {"fused"}
    assert client.get(f"/v1/scenes/{sid}/mesh").status_code == 409
    job = client.post(f"/v1/scenes/{sid}/reconstructions", json={}).json()["job"]
    done = _wait(client, job["id"])
    assert done["state"] == "done", done
    assert done["progress"] == 1.0 and "finished_at" in done
    r = client.get(f"/v1/scenes/{sid}/mesh", params={"format": "ply"})
    assert r.status_code == 200
    etag = r.headers["etag"]
    assert client.get(f"/v1/scenes/{sid}/mesh", headers={"If-None-Match": etag}).status_code == 304
    served = trimesh.load(io.BytesIO(r.content), file_type="ply", process=False)
    # the command line on the same scans and parameters writes the same mesh
    data_dir = tmp_path / "obj"
    write_dataset(data_dir, object_data.sensor, object_data.scans)
    out = tmp_path / "cli.ply"
    args = ["fuse", str(data_dir), "--voxel-size", str(VOXEL), "--mode", "closed", "--quiet"]
    args += ["--tile-size", "8", "--bounds", *map(str, object_data.bounds), "-o", str(out)]
    assert main(args) == 0
    local = trimesh.load(out, process=False)
    assert len(served.faces) == len(local.faces) > 100
    np.testing.assert_array_equal(np.asarray(served.vertices), np.asarray(local.vertices))
    np.testing.assert_array_equal(np.asarray(served.faces), np.asarray(local.faces))
    for fmt in ("obj", "glb", "stl"):
        r = client.get(f"/v1/scenes/{sid}/mesh", params={"format": fmt})
        assert r.status_code == 200 and len(r.content) > 1000
        loaded = trimesh.load(io.BytesIO(r.content), file_type=fmt, process=False)
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.to_geometry()
        assert len(loaded.faces) == len(local.faces)
    png = client.get(f"/v1/scenes/{sid}/slice", params={"axis": "z", "at": 0.1})
    assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
    admin = {"Authorization": f"Bearer {server.read_token('admin')}"}
    metrics = client.get("/metrics", headers=admin).text
    assert 'rangefuse_scans{state="fused"}' in metrics and "rangefuse_tiles" in metrics
    # exact removal through the API
    victim = client.get(f"/v1/scenes/{sid}/scans").json()[0]["id"]
    job = client.delete(f"/v1/scenes/{sid}/scans/{victim}").json()["job"]
    assert _wait(client, job["id"])["state"] == "done"
    assert _n_scans(client, sid) == 3


def test_other_range_formats_are_accepted(client, object_data):
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    _, scan = object_data.scans[0]
    depth = np.where(np.isfinite(scan.range_m), scan.range_m, 0.0)
    png = encode_png(np.round(depth / 0.0002).astype(np.uint16))
    r = _upload(client, sid, png, _meta(scan, depth_scale=0.0002), filename="d.png")
    assert r.status_code == 202, r.text
    buf = io.BytesIO()
    np.savez(buf, range=scan.range_m, pose=scan.T_W_S, sensor=json.dumps(scan.sensor.to_dict()))
    r = _upload(client, sid, buf.getvalue(), json.dumps({}), filename="s.npz")
    assert r.status_code == 202, r.text
    assert _n_scans(client, sid) == 2


def test_idempotency_key_never_creates_a_second_scan(client, object_data):
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    _, scan = object_data.scans[1]
    first = _upload(client, sid, _npy(scan.range_m), _meta(scan), {"Idempotency-Key": "k-1"})
    again = _upload(client, sid, _npy(scan.range_m), _meta(scan), {"Idempotency-Key": "k-1"})
    assert first.status_code == again.status_code == 202
    assert first.json() == again.json()
    assert _n_scans(client, sid) == 1


def _bad_cases(scan):
    """``{case: (multipart files, status, words of the answer)}``: every one a 400."""
    good_meta = _meta(scan)
    good = _npy(scan.range_m)
    pose_nan = scan.T_W_S.copy()
    pose_nan[0, 3] = np.nan
    scaled = scan.T_W_S.copy()
    scaled[:3, :3] *= 2
    pickled = io.BytesIO()
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    sensor = scan.sensor.to_dict()

    def parts(range_bytes: bytes = good, meta: str = good_meta, filename: str = "r.npy") -> dict:
        return {"range": (filename, range_bytes), "meta": (None, meta)}

    def posed(pose: list, **sensor_changes) -> str:
        return json.dumps({"pose": pose, "sensor": {**sensor, **sensor_changes}})

    cases = {
        "no range part": ({"meta": (None, good_meta)}, "range: missing part"),
        "no meta part": ({"range": ("r.npy", good)}, "meta: missing part"),
        "meta not json": (parts(meta="{"), "meta: not valid JSON"),
        "not an array": (parts(b"hello world"), "range: not a .npy"),
        "integer array": (parts(_npy(np.ones((480, 640), np.int32))), "float32"),
        "pickled npy": (parts(pickled.getvalue()), "pickled"),
        "truncated npy": (parts(good[:5000]), "range"),
        "nan pose": (parts(meta=posed(np.nan_to_num(pose_nan, nan=1e400).tolist())), "pose"),
        "non-rigid pose": (parts(meta=posed(scaled.tolist())), "pose"),
        "pose not 4x4": (parts(meta=posed([[1, 0], [0, 1]])), "pose"),
        "wrong shape": (parts(_npy(scan.range_m[:100])), "does not match the sensor"),
        "unknown sensor": (
            parts(meta=posed(scan.T_W_S.tolist(), model="fisheye")),
            "unknown sensor model",
        ),
        "absurd sensor": (parts(meta=posed(scan.T_W_S.tolist(), fx=-5)), "sensor.fx"),
        "negative noise": (parts(meta=_meta(scan, noise={"eps": -1})), "eps"),
        "unknown meta field": (parts(meta=_meta(scan, colour=1)), "meta.colour"),
        "png without scale": (
            parts(encode_png(np.ones((480, 640), np.uint16)), filename="d.png"),
            "depth_scale",
        ),
    }
    return {name: (files, 400, words) for name, (files, words) in cases.items()}


def test_bad_uploads_are_refused_and_nothing_is_stored(client, object_data):
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    _, scan = object_data.scans[0]
    for name, (files, status, words) in _bad_cases(scan).items():
        r = client.post(f"/v1/scenes/{sid}/scans", files=files)
        assert r.status_code == status, (name, r.status_code, r.text)
        assert words in r.json()["detail"], (name, r.json())
    r = client.post(f"/v1/scenes/{sid}/scans", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 400 and "multipart" in r.json()["detail"]
    assert _n_scans(client, sid) == 0
    assert client.get("/healthz").status_code == 200
    assert _n_scans(client, sid) == 0


def test_bad_scenes_and_unknown_ids(client, object_data):
    cases = [
        ({"name": "x", "voxel_size": -1, "mode": "mapping"}, "voxel_size"),
        ({"name": "x", "voxel_size": 0.01, "mode": "closed"}, "bounds"),
        ({"name": "x", "voxel_size": 0.01, "mode": "sideways"}, "mode"),
        ({"name": "x", "voxel_size": 0.01, "bounds": [0, 0, 0, 1, 1]}, "bounds"),
        ({"name": "x", "voxel_size": 0.01, "bounds": [1, 0, 0, 0, 1, 1]}, "x0 must be less"),
        ({"name": "x", "voxel_size": 0.01, "tile_size": 1000}, "tile_size"),
        ({"name": "x", "voxel_size": 0.01, "noise": {"rho": 0.7}}, "rho"),
        ({"name": "x", "voxel_size": 0.01, "colour": "red"}, "colour"),
        ({"voxel_size": 0.01}, "name"),
    ]
    before = len(client.get("/v1/scenes").json())
    for body, words in cases:
        r = client.post("/v1/scenes", json=body)
        assert r.status_code == 422, (body, r.text)
        assert words in r.json()["detail"], (body, r.json())
    assert len(client.get("/v1/scenes").json()) == before
    assert client.get("/v1/scenes/nope").status_code == 404
    assert client.get("/v1/jobs/nope").status_code == 404
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    assert client.get(f"/v1/scenes/{sid}/scans/nope").status_code == 404
    assert client.delete(f"/v1/scenes/{sid}/scans/nope").status_code == 404
    assert client.get(f"/v1/scenes/{sid}/mesh", params={"format": "vtk"}).status_code == 422
    r = client.get(f"/v1/scenes/{sid}/slice", params={"axis": "w", "at": 0})
    assert r.status_code == 422
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert client.get(f"/v1/scenes/{sid}").status_code == 404


def test_oversized_and_short_bodies(server, client, object_data):
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    big = b"\0" * int(9 * 2**20)
    r = client.post(
        f"/v1/scenes/{sid}/scans", files={"range": ("r.npy", big), "meta": (None, "{}")}
    )
    assert r.status_code == 413 and "limit" in r.json()["detail"]

    def chunks():  # no Content-Length: the limit applies while streaming
        yield b'--xyz\r\nContent-Disposition: form-data; name="range"; filename="r.npy"\r\n\r\n'
        for _ in range(12):
            yield b"\0" * 2**20

    r = client.post(
        f"/v1/scenes/{sid}/scans",
        content=chunks(),
        headers={"content-type": "multipart/form-data; boundary=xyz"},
    )
    assert r.status_code == 413, r.text
    # a body that claims more than it sends, then the client goes away
    with socket.create_connection(("127.0.0.1", server.port)) as s:
        s.sendall(
            f"POST /v1/scenes/{sid}/scans HTTP/1.1\r\nHost: x\r\n"
            f"Authorization: Bearer {server.token}\r\n"
            "Content-Type: multipart/form-data; boundary=xyz\r\nContent-Length: 100000\r\n\r\n"
            '--xyz\r\nContent-Disposition: form-data; name="meta"\r\n\r\n{}'.encode()
        )
    time.sleep(0.5)
    assert client.get("/healthz").status_code == 200
    assert _n_scans(client, sid) == 0


def test_malformed_multipart_bodies(client, object_data):
    """The body is parsed as it streams in (not by Starlette's form parser): every malformed
    one is a 400 naming the problem, and nothing is stored."""
    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    url = f"/v1/scenes/{sid}/scans"

    def part(name: str, body: bytes = b"x") -> bytes:
        return (f'--b\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n'.encode()
                + body + b"\r\n")  # fmt: skip

    cases = {
        "no boundary": ("multipart/form-data", part("range") + b"--b--\r\n", "multipart"),
        "not multipart": ("application/json", b"{}", "multipart/form-data"),
        "garbage": ("multipart/form-data; boundary=b", b"\x00garbage\r\n--", "malformed"),
        "five parts": (
            "multipart/form-data; boundary=b",
            b"".join(part(f"p{i}") for i in range(5)) + b"--b--\r\n",
            "more than 4 parts",
        ),
        "no meta": ("multipart/form-data; boundary=b", part("range") + b"--b--\r\n", "meta"),
    }
    for what, (ctype, body, message) in cases.items():
        r = client.post(url, content=body, headers={"content-type": ctype})
        assert r.status_code == 400, (what, r.text)
        assert message in r.json()["detail"], (what, r.text)
    assert _n_scans(client, sid) == 0


def test_tokens_and_tenants(server, client, object_data):
    assert httpx.get(f"{server.url}/v1/scenes").status_code == 401
    bad = httpx.get(f"{server.url}/v1/scenes", headers={"Authorization": "Bearer nope"})
    assert bad.status_code == 401 and "invalid token" in bad.json()["detail"]
    # a second tenant (the token command writes to the same store)
    out = subprocess.run(
        [sys.executable, "-m", "rangefuse.service.cli", "token", "create", "--tenant", "other",
         "--data-dir", str(server.data_dir)],
        cwd=ROOT, capture_output=True, text=True, check=True,
    )  # fmt: skip
    other = {"Authorization": f"Bearer {out.stdout.strip()}"}
    mine = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    theirs = httpx.get(f"{server.url}/v1/scenes", headers=other).json()
    assert mine not in {s["id"] for s in theirs}
    assert httpx.get(f"{server.url}/v1/scenes/{mine}", headers=other).status_code == 404
    job = client.post(f"/v1/scenes/{mine}/reconstructions", json={}).json()["job"]["id"]
    assert httpx.get(f"{server.url}/v1/jobs/{job}", headers=other).status_code == 404


def test_concurrent_uploads_are_fused_exactly_once(server, client, object_data):
    import threading

    from rangefuse.engine import Volume
    from rangefuse.storage import Store, open_scene

    sid = client.post("/v1/scenes", json=_scene_body(object_data)).json()["id"]
    statuses: list[int] = []

    def one_client() -> None:
        with httpx.Client(base_url=server.url, headers=client.headers, timeout=120) as c:
            for _, scan in object_data.scans:
                statuses.append(_upload(c, sid, _npy(scan.range_m), _meta(scan)).status_code)

    threads = [threading.Thread(target=one_client) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert statuses == [202] * 16
    deadline = time.time() + 300
    while {s["state"] for s in client.get(f"/v1/scenes/{sid}/scans").json()} != {"fused"}:
        assert time.time() < deadline
        time.sleep(0.2)
    assert _n_scans(client, sid) == 16
    with Store.open(server.data_dir) as store, open_scene(store, sid, wait=True) as scene:
        served = scene.to_dense()
        volume = Volume(scene.grid, scene.params)
    volume.add_many(
        [(f"{k}-{n}", s) for k in range(4) for n, (_, s) in enumerate(object_data.scans)]
    )
    assert np.array_equal(volume.to_dense().logodds, served.logodds, equal_nan=True)


@pytest.mark.slow
def test_restart_resumes_an_interrupted_reconstruction(tmp_path, object_data):
    srv = Server(tmp_path / "data").start()
    token = srv.read_token()
    headers = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=srv.url, headers=headers, timeout=60) as c:
        body = _scene_body(object_data, voxel_size=0.006, tile_size=16)
        sid = c.post("/v1/scenes", json=body).json()["id"]
        for _, scan in object_data.scans:
            assert _upload(c, sid, _npy(scan.range_m), _meta(scan)).status_code == 202
        job = c.post(f"/v1/scenes/{sid}/reconstructions", json={}).json()["job"]["id"]
        deadline = time.time() + 60
        while c.get(f"/v1/jobs/{job}").json()["state"] == "queued" and time.time() < deadline:
            time.sleep(0.01)
        assert c.get(f"/v1/jobs/{job}").json()["state"] == "running"
    srv.kill()  # mid-job
    srv = Server(tmp_path / "data").start()
    try:
        with httpx.Client(base_url=srv.url, headers=headers, timeout=60) as c:
            assert _wait(c, job, timeout=300)["state"] == "done"
            assert c.get(f"/v1/scenes/{sid}/mesh").status_code == 200
            assert {s["state"] for s in c.get(f"/v1/scenes/{sid}/scans").json()} == {"fused"}
    finally:
        srv.stop()
