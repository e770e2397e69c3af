#!/usr/bin/env python3
"""End-to-end test of the container stack (docker/compose.yaml), run by ``make test-docker``.

Starts the stack (API, Dask scheduler, two Dask workers, one shared volume) from an image
that is already built, then, with a real HTTP client on the published port:

1. creates a scene, uploads the scans of ``rangefuse synth object --views N``, asks for a
   reconstruction, waits for the scene's jobs and downloads the mesh (PLY);
2. does the same on a fresh scene, and ``docker kill``s the container of a worker that the
   scheduler shows running units of one of the scene's jobs (watched from inside the
   scheduler's container); the jobs must still complete, on the surviving worker, and the
   mesh must be byte-identical to the first one;
3. starts the killed worker again and waits until the cluster has two workers again.

Everything the stack made (containers, network, volume) is removed at the end, also when a
step fails; the logs of every service are printed first when one does. Each step prints
how long it took. Exit status 0 when every check passed, 1 otherwise.

    .venv/bin/python docker/test_stack.py --image rangefuse:latest [--compose "docker compose"]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parent.parent
COMPOSE_FILE = REPO / "docker" / "compose.yaml"
TERMINAL = {"done", "failed", "cancelled"}


class CheckError(Exception):
    """A check of the test failed (the message says which and what was seen)."""


# --- reporting ---------------------------------------------------------------------------------


class Steps:
    """Prints each step as it starts and ends, and a table of durations at the end."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.rows: list[tuple[str, float, str]] = []

    def log(self, text: str) -> None:
        print(f"[{time.perf_counter() - self.t0:7.1f} s] {text}", flush=True)

    @contextmanager
    def step(self, name: str) -> Iterator[dict[str, str]]:
        note: dict[str, str] = {}
        self.log(f"{name} ...")
        t = time.perf_counter()
        status = "FAILED"
        try:
            yield note
            status = "ok"
        except Exception as exc:  # the reason goes in the summary, which CI's tail keeps
            note.setdefault("detail", " ".join(str(exc).split())[:400])
            raise
        finally:
            dt = time.perf_counter() - t
            detail = note.get("detail", "")
            self.rows.append((name, dt, status if not detail else f"{status}: {detail}"))
            self.log(f"{name}: {status} in {dt:.1f} s{': ' + detail if detail else ''}")

    def summary(self) -> None:
        print("\ntest-docker: steps", flush=True)
        width = max((len(r[0]) for r in self.rows), default=10)
        for name, dt, status in self.rows:
            print(f"  {name:<{width}}  {dt:7.1f} s  {status}")
        print(f"  {'total':<{width}}  {time.perf_counter() - self.t0:7.1f} s", flush=True)


# --- the stack ---------------------------------------------------------------------------------


def run(
    cmd: list[str],
    *,
    check: bool = True,
    capture: bool = True,
    env: dict[str, str] | None = None,
    timeout: float = 600,
) -> str:
    proc = subprocess.run(
        cmd,
        env=env,
        timeout=timeout,
        text=True,
        stdout=subprocess.PIPE if capture else None,
        stderr=subprocess.STDOUT if capture else None,
    )
    if check and proc.returncode != 0:
        out = (proc.stdout or "").strip()
        raise CheckError(
            f"`{shlex.join(cmd)}` exited with {proc.returncode}"
            + (f":\n{out[-3000:]}" if out else "")
        )
    return proc.stdout or ""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Stack:
    """One compose project of docker/compose.yaml, found again by its labels."""

    def __init__(self, compose: list[str], project: str, image: str, port: int) -> None:
        self.compose_cmd = compose
        self.project = project
        self.env = dict(os.environ, RANGEFUSE_IMAGE=image, RANGEFUSE_API_PORT=str(port))

    def compose(self, *args: str, check: bool = True, timeout: float = 600) -> str:
        cmd = [*self.compose_cmd, "-p", self.project, "-f", str(COMPOSE_FILE), *args]
        return run(cmd, check=check, env=self.env, timeout=timeout)

    def _label(self, service: str | None = None) -> list[str]:
        flags = ["--filter", f"label=com.docker.compose.project={self.project}"]
        if service:
            flags += ["--filter", f"label=com.docker.compose.service={service}"]
        return flags

    def containers(self, service: str, *, all_states: bool = False) -> list[str]:
        """Names of the service's containers (running ones unless ``all_states``), sorted."""
        out = run(
            [
                "docker",
                "ps",
                *(["-a"] if all_states else []),
                *self._label(service),
                "--format",
                "{{.Names}}",
            ]
        )
        return sorted(out.split())

    def exec(self, service: str, *cmd: str) -> str:
        (name,) = self.containers(service)[:1] or [None]
        if name is None:
            raise CheckError(f"no running {service} container")
        return run(["docker", "exec", name, *cmd])

    def leftovers(self) -> list[str]:
        """Containers, networks and volumes of the project that still exist."""
        found = []
        for kind, cmd, fmt in (
            ("container", ["docker", "ps", "-a"], "{{.Names}}"),
            ("network", ["docker", "network", "ls"], "{{.Name}}"),
            ("volume", ["docker", "volume", "ls"], "{{.Name}}"),
        ):
            out = run([*cmd, *self._label(), "--format", fmt], check=False)
            found += [f"{kind} {n}" for n in out.split()]
        return found

    def logs(self) -> str:
        return self.compose("logs", "--no-color", "--tail", "60", check=False, timeout=60)

    def down(self) -> None:
        self.compose("down", "-v", "--remove-orphans", "-t", "10", check=False, timeout=180)
        # Anything compose did not remove (a container started outside it): by label.
        for line in self.leftovers():
            kind, name = line.split(" ", 1)
            rm = {
                "container": ["docker", "rm", "-f", "-v"],
                "network": ["docker", "network", "rm"],
                "volume": ["docker", "volume", "rm", "-f"],
            }[kind]
            run([*rm, name], check=False)


# --- the API -----------------------------------------------------------------------------------


class Api:
    def __init__(self, base_url: str) -> None:
        self.http = httpx.Client(base_url=base_url, timeout=httpx.Timeout(60.0, connect=5.0))

    def authorize(self, token: str) -> None:
        self.http.headers["Authorization"] = f"Bearer {token}"

    def _json(self, resp: httpx.Response, expect: int) -> Any:
        if resp.status_code != expect:
            raise CheckError(
                f"{resp.request.method} {resp.request.url.path}: expected "
                f"{expect}, got {resp.status_code}: {resp.text[:500]}"
            )
        return resp.json() if resp.content else None

    def health(self) -> tuple[int, dict[str, Any]]:
        try:
            resp = self.http.get("/healthz", timeout=5.0)
        except httpx.HTTPError as exc:
            return 0, {"error": type(exc).__name__}
        try:
            body = resp.json()
        except ValueError:
            body = {"text": resp.text[:200]}
        return resp.status_code, body if isinstance(body, dict) else {"body": body}

    def wait_healthy(self, workers: int, timeout: float) -> dict[str, Any]:
        """Until /healthz answers 200 with ``workers`` Dask workers (when it reports them)."""
        deadline = time.monotonic() + timeout
        status, body = 0, {}
        while time.monotonic() < deadline:
            status, body = self.health()
            if status == 200 and (workers == 0 or body.get("workers") == workers):
                return body
            time.sleep(0.5)
        raise CheckError(
            f"/healthz: no answer 200 with {workers} workers in {timeout:.0f} s "
            f"(last: {status} {body})"
        )

    def create_scene(self, name: str, params: dict[str, Any]) -> str:
        scene = self._json(self.http.post("/v1/scenes", json={"name": name, **params}), 201)
        return str(scene["id"])

    def upload(self, scene: str, path: Path, sensor: dict[str, Any]) -> str:
        meta = json.dumps({"name": path.stem, "sensor": sensor})
        with path.open("rb") as f:
            resp = self.http.post(
                f"/v1/scenes/{scene}/scans",
                data={"meta": meta},
                files={"range": (path.name, f, "application/octet-stream")},
            )
        return str(self._json(resp, 202)["job"]["id"])

    def reconstruct(self, scene: str) -> str:
        body = self._json(self.http.post(f"/v1/scenes/{scene}/reconstructions", json={}), 202)
        return str(body["job"]["id"])

    def scene_jobs(self, scene: str) -> list[dict[str, Any]]:
        jobs = self._json(self.http.get("/v1/jobs", params={"limit": 1000}), 200)
        return [j for j in jobs if j.get("scene_id") == scene]

    def wait_jobs(self, scene: str, timeout: float) -> list[dict[str, Any]]:
        """Until every job of the scene has ended; each must be ``done``."""
        deadline = time.monotonic() + timeout
        while True:
            jobs = self.scene_jobs(scene)
            if jobs and all(j["state"] in TERMINAL for j in jobs):
                bad = [j for j in jobs if j["state"] != "done"]
                if bad:
                    raise CheckError(
                        "jobs did not complete: "
                        + "; ".join(
                            f"{j['kind']} {j['id']} {j['state']}: {j.get('error')}" for j in bad
                        )
                    )
                return jobs
            if time.monotonic() > deadline:
                raise CheckError(
                    f"jobs still not done after {timeout:.0f} s: "
                    + ", ".join(f"{j['kind']} {j['state']} {j['progress']:.2f}" for j in jobs)
                )
            time.sleep(0.2)

    def mesh(self, scene: str) -> bytes:
        resp = self.http.get(f"/v1/scenes/{scene}/mesh", params={"format": "ply"})
        if resp.status_code != 200:
            raise CheckError(f"mesh: expected 200, got {resp.status_code}: {resp.text[:300]}")
        return resp.content


def ply_faces(data: bytes) -> int:
    """The face count of a PLY's header (checks that it is one)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise CheckError(f"mesh: not a PLY file (starts {data[:20]!r})")
    for line in data[:end].decode("ascii", "replace").splitlines():
        if line.startswith("element face "):
            return int(line.split()[2])
    raise CheckError("mesh: the PLY header has no face element")


# --- the test ----------------------------------------------------------------------------------


#: Run in the scheduler's container (``python3 -c WATCH_SCHEDULER``): prints "ready" once
#: connected, then every 50 ms, while some worker has tasks, ``{worker address: tasks}`` as
#: a JSON line; exits when its standard input closes.
WATCH_SCHEDULER = """
import json, os, sys, threading, time
from distributed import Client
threading.Thread(target=lambda: (sys.stdin.read(), os._exit(0)), daemon=True).start()
with Client("tcp://127.0.0.1:8786", timeout=30) as client:
    print("ready", flush=True)
    while True:
        busy = {w: len(keys) for w, keys in client.processing().items() if keys}
        if busy:
            print(json.dumps(busy), flush=True)
        time.sleep(0.05)
"""


class Killer(threading.Thread):
    """``docker kill``s the container of a worker that the scheduler shows running units of
    a job of the scene, once that job has been running for ``delay`` seconds."""

    def __init__(self, api: Api, stack: Stack, scene: str, steps: Steps, delay: float) -> None:
        super().__init__(daemon=True)
        self.api, self.scene, self.steps, self.delay = api, scene, steps, delay
        self.killed: dict[str, Any] | None = None
        self.error: BaseException | None = None
        self.containers = {}  # the workers' addresses on the stack's network -> container
        for name in stack.containers("worker"):
            fmt = "{{range .NetworkSettings.Networks}}{{.IPAddress}} {{end}}"
            for ip in run(["docker", "inspect", "-f", fmt, name]).split():
                self.containers[ip] = name
        (scheduler,) = stack.containers("scheduler")
        self.watch = subprocess.Popen(
            ["docker", "exec", "-i", scheduler, "python3", "-c", WATCH_SCHEDULER],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        assert self.watch.stdout is not None
        first = self.watch.stdout.readline().strip()
        if first != "ready":
            self.close()
            raise CheckError(f"watching the scheduler: {first or 'no answer'}")

    def close(self) -> None:
        if self.watch.stdin:
            self.watch.stdin.close()  # the watcher exits
        try:
            self.watch.wait(10)
        except subprocess.TimeoutExpired:
            self.watch.kill()

    def _running_job(self) -> dict[str, Any] | None:
        return next((j for j in self.api.scene_jobs(self.scene) if j["state"] == "running"), None)

    def run(self) -> None:
        assert self.watch.stdout is not None
        seen: dict[str, float] = {}
        try:
            for line in self.watch.stdout:
                if not line.startswith("{"):
                    continue
                busy: dict[str, int] = json.loads(line)
                job = self._running_job()
                if job is None:
                    continue
                ran = time.monotonic() - seen.setdefault(job["id"], time.monotonic())
                address, tasks = max(busy.items(), key=lambda item: item[1])
                victim = self.containers.get(address.split("://")[-1].rsplit(":", 1)[0])
                if ran < self.delay or victim is None:
                    continue
                sent = time.time()
                run(["docker", "kill", victim])
                self.killed = {
                    "sent": sent, "at": time.time(), "victim": victim, "tasks": tasks, "ran": ran,
                    "job": job["id"], "kind": job["kind"], "progress": job["progress"],
                }  # fmt: skip
                self.steps.log(
                    f"docker kill {victim}: it had {tasks} unit(s) of the {job['kind']} job "
                    f"{job['id']} (running for {ran:.1f} s, progress {job['progress']:.2f})"
                )
                break
        except BaseException as exc:  # reported by the main thread
            self.error = exc


def reconstruct_scene(
    api: Api, name: str, params: dict[str, Any], scans: list[Path], sensor: dict[str, Any]
) -> str:
    """Create a scene, upload the scans and ask for a reconstruction; returns the scene."""
    scene = api.create_scene(name, params)
    for path in scans:
        api.upload(scene, path, sensor)
    api.reconstruct(scene)
    return scene


class Run:
    """The checks, in order, on one stack; each is a step, and stops the run when it fails."""

    CHECKS = ("scene 1 end to end", "scene 2 with a worker killed", "worker back", "tear down")

    def __init__(self, args: argparse.Namespace, steps: Steps) -> None:
        self.args, self.steps = args, steps
        self.port = free_port()
        self.stack = Stack(shlex.split(args.compose), args.project, args.image, self.port)
        self.api = Api(f"http://127.0.0.1:{self.port}")
        self.params: dict[str, Any] = {
            "voxel_size": args.voxel_size,
            "mode": "closed",
            "max_discontinuity": 0.05,
        }
        self.passed: list[str] = []
        self.failed: list[str] = []

    def start(self, tmp: Path) -> tuple[list[Path], dict[str, Any]]:
        """Stack up, a token, and the synthetic scans (made in the api container)."""
        args, stack = self.args, self.stack
        with self.steps.step("stack up (compose up, /healthz)") as note:
            stack.down()  # whatever an earlier run may have left
            stack.compose("up", "-d")
            note["detail"] = str(self.api.wait_healthy(args.workers, timeout=180))
        with self.steps.step("token (rangefuse token create in the api container)"):
            token = stack.exec("api", "rangefuse", "token", "create", "--tenant", "e2e")
            self.api.authorize(token.strip().splitlines()[-1])
        with self.steps.step(
            f"synthetic scans (rangefuse synth object --views {args.views})"
        ) as note:
            inside = "/tmp/e2e-object"
            stack.exec("api", "rm", "-rf", inside)
            stack.exec("api", "rangefuse", "synth", "object", inside, "--views", str(args.views))
            run(["docker", "cp", f"{stack.containers('api')[0]}:{inside}", str(tmp / "object")])
            scans = sorted((tmp / "object" / "scans").glob("scan_*.npz"))
            sensor = json.loads((tmp / "object" / "sensor.json").read_text())
            # Closed mode over REST needs the region of interest: the one synth wrote.
            self.params["bounds"] = json.loads((tmp / "object" / "scene.json").read_text())[
                "bounds"
            ]
            size = sum(p.stat().st_size for p in scans) / 1e6
            note["detail"] = f"{len(scans)} scans, {size:.1f} MB"
        return scans, sensor

    def scene1(self, scans: list[Path], sensor: dict[str, Any]) -> bytes:
        with self.steps.step("scene 1: create, upload, reconstruct, download") as note:
            scene = reconstruct_scene(self.api, "e2e-1", self.params, scans, sensor)
            jobs = self.api.wait_jobs(scene, self.args.job_timeout)
            mesh = self.api.mesh(scene)
            note["detail"] = (
                f"{len(jobs)} jobs done, {ply_faces(mesh)} faces, {len(mesh)} bytes, "
                f"sha256 {hashlib.sha256(mesh).hexdigest()[:16]}"
            )
        self.passed.append(self.CHECKS[0])
        return mesh

    def scene2(self, scans: list[Path], sensor: dict[str, Any], mesh1: bytes) -> str:
        """Scene 2 with one worker container killed mid-job; returns the killed one."""
        args, api, stack = self.args, self.api, self.stack
        with self.steps.step("scene 2: the same, one worker killed mid-job") as note:
            workers = stack.containers("worker")
            if len(workers) != args.workers:
                raise CheckError(f"expected {args.workers} worker containers, found {workers}")
            scene = api.create_scene("e2e-2", self.params)
            killer = Killer(api, stack, scene, self.steps, args.kill_after)
            killer.start()
            try:
                for path in scans:
                    api.upload(scene, path, sensor)
                api.reconstruct(scene)
                jobs = api.wait_jobs(scene, args.job_timeout)
            finally:
                killer.close()
                killer.join(10)
            if killer.error is not None:
                raise CheckError(f"watching the jobs failed: {killer.error!r}")
            if killer.killed is None:
                raise CheckError(
                    "no worker was seen running a unit of a job of scene 2 for "
                    f"{args.kill_after} s, so none was killed (the jobs are too short: try "
                    "a smaller --voxel-size or a shorter --kill-after)"
                )
            k = killer.killed
            job = next(j for j in jobs if j["id"] == k["job"])
            after = (job.get("finished_at") or 0.0) - k["at"]
            if after < k["sent"] - k["at"]:
                raise CheckError(
                    f"the {k['kind']} job had finished before `docker kill` was called "
                    f"({-after:.2f} s before it returned; the call took "
                    f"{k['at'] - k['sent']:.2f} s)"
                )
            mesh = api.mesh(scene)
            if mesh != mesh1:
                raise CheckError(
                    f"the meshes differ: {len(mesh1)} bytes, sha256 "
                    f"{hashlib.sha256(mesh1).hexdigest()} (scene 1) vs {len(mesh)} bytes, "
                    f"sha256 {hashlib.sha256(mesh).hexdigest()} (scene 2)"
                )
            victim = k["victim"]
            state = run(["docker", "inspect", "-f", "{{.State.Status}}", victim]).strip()
            note["detail"] = (
                f"killed {victim}, which had {k['tasks']} unit(s) of the {k['kind']} job "
                f"(running for {k['ran']:.1f} s, progress {k['progress']:.2f}); the job "
                f"finished {after:.1f} s later; "
                f"{len(jobs)} jobs done; the mesh is byte-identical to scene 1's; "
                f"{victim} is {state}, /healthz {api.health()[1]}"
            )
        self.passed.append(self.CHECKS[1])
        return victim

    def worker_back(self, victim: str) -> None:
        with self.steps.step("worker back (docker start), /healthz") as note:
            run(["docker", "start", victim])
            note["detail"] = str(self.api.wait_healthy(self.args.workers, timeout=120))
        self.passed.append(self.CHECKS[2])

    def tear_down(self) -> None:
        with self.steps.step("tear down (compose down -v)") as note:
            self.stack.down()
            left = self.stack.leftovers()
            note["detail"] = "nothing left" if not left else f"left behind: {left}"
            if left:
                raise CheckError(f"left behind after compose down: {left}")
        self.passed.append(self.CHECKS[3])

    def __call__(self) -> bool:
        args = self.args
        self.steps.log(
            f"image {args.image}, compose `{args.compose}`, project {args.project}, "
            f"API on 127.0.0.1:{self.port}"
        )
        try:
            with tempfile.TemporaryDirectory(prefix="rangefuse-e2e-") as tmp:
                scans, sensor = self.start(Path(tmp))
                mesh1 = self.scene1(scans, sensor)
                victim = self.scene2(scans, sensor, mesh1)
                self.worker_back(victim)
        except Exception as exc:
            self.failed.append(self.CHECKS[len(self.passed)])
            print(f"\ntest-docker: FAILED: {exc}", file=sys.stderr, flush=True)
            print("\n--- logs of the stack (last lines of each service) ---", file=sys.stderr)
            print(self.stack.logs(), file=sys.stderr, flush=True)
        finally:
            if args.keep:
                self.steps.log(f"--keep: the stack stays up (project {args.project})")
            else:
                try:
                    self.tear_down()
                except Exception as exc:
                    self.failed.append(self.CHECKS[-1])
                    print(f"test-docker: FAILED: {exc}", file=sys.stderr, flush=True)
        return not self.failed


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--image", default="rangefuse:latest", help="image to run (built already)")
    ap.add_argument(
        "--compose",
        default=os.environ.get("COMPOSE", "docker compose"),
        help="compose command: docker compose, docker-compose (env COMPOSE)",
    )
    ap.add_argument("--project", default="rangefuse-e2e", help="compose project name")
    ap.add_argument("--views", type=int, default=6, help="scans of the synthetic object")
    ap.add_argument("--voxel-size", type=float, default=0.003, help="scene voxel size (m)")
    ap.add_argument("--workers", type=int, default=2, help="Dask workers the stack starts")
    ap.add_argument("--job-timeout", type=float, default=600.0, help="seconds per scene")
    ap.add_argument(
        "--kill-after",
        type=float,
        default=0.5,
        help="kill a busy worker once a job of scene 2 has run this long (s)",
    )
    ap.add_argument("--keep", action="store_true", help="leave the stack up at the end")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    steps = Steps()
    checks = Run(parse_args(argv), steps)
    ok = checks()
    steps.summary()
    skipped = len(Run.CHECKS) - len(checks.passed) - len(checks.failed)
    print(
        f"\ntest-docker: {len(checks.passed)} passed, {len(checks.failed)} failed"
        + (f", {skipped} skipped" if skipped else ""),
        flush=True,
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
