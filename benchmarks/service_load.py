"""Load on the REST service: concurrent clients uploading scans (issue: REST service).

Starts ``rangefuse serve`` on loopback with a fresh store, creates a scene (the synthetic
object, closed mode), and has N clients upload M scans each at the same time. Prints upload
latency (p50, p99), uploads/s, the time until every scan is fused, and checks that every
scan was fused exactly once: the scene's volume equals, bit for bit, the in-memory fusion
of all uploaded scans.

    python benchmarks/service_load.py                 # 8 clients x 25 scans
    python benchmarks/service_load.py --quick         # 2 clients x 3 scans
"""

from __future__ import annotations

import argparse
import io
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import httpx
import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--scans", type=int, default=25, help="per client")
    parser.add_argument("--voxel", type=float, default=0.04)
    parser.add_argument(
        "--http-processes", type=int, default=os.cpu_count() or 1,
        help="the service's HTTP processes (default: one per core)",
    )  # fmt: skip
    args = parser.parse_args()
    clients, per = (2, 3) if args.quick else (args.clients, args.scans)
    sys.path.insert(0, str(ROOT))
    from rangefuse.engine import Volume
    from rangefuse.engine.synth import make_dataset
    from rangefuse.storage import Store, open_scene

    data = make_dataset("object", views=per)
    payloads = []
    for _, scan in data.scans:
        buf = io.BytesIO()
        np.save(buf, scan.range_m)
        meta = json.dumps({"pose": scan.T_W_S.tolist(), "sensor": scan.sensor.to_dict()})
        payloads.append((buf.getvalue(), meta))
    with tempfile.TemporaryDirectory() as tmp:
        port = _port()
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "RANGEFUSE_POLL_S": "0.05"}
        proc = subprocess.Popen(
            [sys.executable, "-m", "rangefuse.service.cli", "serve", "--data-dir", f"{tmp}/data",
             "--port", str(port), "--http-processes", str(args.http_processes)],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        try:
            token = ""
            assert proc.stdout is not None
            while not token:
                line = proc.stdout.readline()
                if not line:
                    raise SystemExit("the server did not start")
                if "created a token" in line:
                    token = line.rsplit(" ", 1)[1].strip()
            # keep reading the server's log (a full pipe would block its logging), the last
            # lines kept for a failure's diagnosis
            log_tail: deque[str] = deque(maxlen=200)
            threading.Thread(target=log_tail.extend, args=(proc.stdout,), daemon=True).start()
            url = f"http://127.0.0.1:{port}"
            headers = {"Authorization": f"Bearer {token}"}
            _wait_until_settled(url, proc.pid)
            body = {"name": "load", "voxel_size": args.voxel, "mode": "closed",
                    "bounds": list(data.bounds)}  # fmt: skip
            sid = httpx.post(f"{url}/v1/scenes", json=body, headers=headers).json()["id"]
            cpu_before = _cpu_by_role(proc.pid)
            t0 = time.perf_counter()
            latencies, statuses, refusals = _upload_all(url, headers, sid, payloads, clients)
            upload_s = time.perf_counter() - t0
            cpu_after = _cpu_by_role(proc.pid)
            with httpx.Client(base_url=url, headers=headers, timeout=60) as c:
                while True:
                    scans = c.get(f"/v1/scenes/{sid}/scans").json()
                    if all(s["state"] == "fused" for s in scans):
                        break
                    time.sleep(0.2)
            fused_s = time.perf_counter() - t0
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        with Store.open(f"{tmp}/data") as store, open_scene(store, sid) as scene:
            served = scene.to_dense()
            grid, params = scene.grid, scene.params
        volume = Volume(grid, params)
        volume.add_many(
            [(f"{c}-{k}", scan) for c in range(clients) for k, (_, scan) in enumerate(data.scans)]
        )
        exact = np.array_equal(volume.to_dense().logodds, served.logodds, equal_nan=True)
    for refusal in sorted(set(refusals))[:5]:
        print("refused:", refusal)
    if refusals or not exact:
        print("the server's last log lines:\n" + "".join(list(log_tail)[-40:]))
    cpu = {role: cpu_after[role] - cpu_before.get(role, 0.0) for role in cpu_after}
    print(f"{clients} clients x {per} scans of 640x480 (1.2 MB .npy each), voxel {args.voxel} m, "
          f"{args.http_processes} HTTP processes")  # fmt: skip
    _table(latencies, statuses, upload_s, fused_s, exact, cpu)


def _wait_until_settled(url: str, server_pid: int, timeout: float = 120.0) -> None:
    """Until every worker has joined (``/healthz`` 200 with the workers the service starts)
    and the service's processes are about idle (less than 15% of a core over half a second;
    idle, the scheduler, nannies and workers take about 9%): the load starts on a service
    that has finished starting, not on workers still importing."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            r = httpx.get(f"{url}/healthz", timeout=1)
            if r.status_code == 200 and r.json()["workers"] >= int(
                os.environ.get("RANGEFUSE_WORKERS", "2")
            ):
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    else:
        raise SystemExit("the service's workers did not start")
    before = sum(_cpu_by_role(server_pid).values())
    while time.monotonic() < deadline:
        time.sleep(0.5)
        after = sum(_cpu_by_role(server_pid).values())
        if after - before < 0.075:
            return
        before = after
    raise SystemExit("the service did not settle")


def _upload_all(
    url: str, headers: dict[str, str], sid: str, payloads: list[tuple[bytes, str]], clients: int
) -> tuple[list[float], list[int], list[str]]:
    """Each of ``clients`` threads uploads every payload; returns the latencies, the statuses
    (0: no answer) and the refusals' texts."""
    latencies: list[float] = []
    statuses: list[int] = []
    refusals: list[str] = []
    lock = threading.Lock()

    def client() -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
            for rng, meta in payloads:
                t0 = time.perf_counter()
                try:
                    r = c.post(
                        f"/v1/scenes/{sid}/scans",
                        files={"range": ("r.npy", rng), "meta": (None, meta)},
                    )
                except httpx.HTTPError as exc:  # counted, as a refusal
                    with lock:
                        statuses.append(0)
                        refusals.append(f"no answer: {exc!r}")
                    continue
                with lock:
                    latencies.append(time.perf_counter() - t0)
                    statuses.append(r.status_code)
                    if r.status_code != 202:
                        refusals.append(f"{r.status_code} {r.text[:300]}")

    threads = [threading.Thread(target=client) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return latencies, statuses, refusals


def _table(
    latencies: list[float],
    statuses: list[int],
    upload_s: float,
    fused_s: float,
    exact: bool,
    cpu: dict[str, float],
) -> None:
    """Print the run's row and the CPU each role used per upload."""
    n = len(statuses)
    lat = np.array(latencies) * 1000
    ok = sum(1 for s in statuses if s == 202)
    five = sum(1 for s in statuses if s >= 500)
    print(f"{'uploads':>7} {'202':>5} {'5xx':>4} {'p50 ms':>7} {'p99 ms':>7} {'uploads/s':>9} "
          f"{'all fused s':>11} {'scans/s fused':>13} {'exactly once':>12}")  # fmt: skip
    print(
        f"{n:7d} {ok:5d} {five:4d} {np.percentile(lat, 50):7.1f} {np.percentile(lat, 99):7.1f} "
        f"{n / upload_s:9.1f} {fused_s:11.1f} {n / fused_s:13.1f} {exact!s:>12}"
    )
    cores = os.cpu_count() or 1
    print(f"CPU while uploading ({upload_s:.2f} s wall x {cores} cores = "
          f"{cores * upload_s:.2f} s), ms per upload:")  # fmt: skip
    print("  " + "  ".join(f"{role} {1000 * s / n:.1f}" for role, s in sorted(cpu.items())))


def _cpu_by_role(server_pid: int) -> dict[str, float]:
    """CPU seconds (user + system) used so far by this process (the clients), the API
    processes (the service's and the other HTTP processes it started), and its other children
    (the Dask scheduler and workers, nannies included)."""
    out = {"clients": sum(psutil.Process().cpu_times()[:2])}
    api = psutil.Process(server_pid)
    out["api"] = sum(api.cpu_times()[:2])
    for child in api.children(recursive=True):
        try:
            cmd = " ".join(child.cmdline())
            role = (
                "scheduler" if "dask_scheduler" in cmd
                else "api" if "http_processes" in cmd
                else "workers"
            )  # fmt: skip
            out[role] = out.get(role, 0.0) + sum(child.cpu_times()[:2])
        except psutil.NoSuchProcess:
            continue
    return out


if __name__ == "__main__":
    main()
