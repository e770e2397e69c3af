"""Frames per second of the web page's viewer while orbiting, in headless Chromium with
software WebGL (SwiftShader), for the preview and for the full mesh (issue 20, "Must show").

Starts ``rangefuse serve`` on loopback with a fresh store, fuses the synthetic room at 1 cm
(a mapping scene; ``--views`` sets how much of it is seen, hence the faces), lets the
reconstruction job make its preview, then opens the page in Chromium and orbits the camera
one step per animation frame for ``--seconds`` (viewer.orbit: requestAnimationFrame, a
programmatic rotation, a render each frame), twice per mesh: as the page does when a person
drags (the preview's coarse level at half resolution while moving; the mesh shown at rest
comes back when the camera stops), and drawing every face of the mesh at full resolution
throughout. Prints faces, load
time (download and decoding to GPU buffers) and frames per second; saves screenshots of the
page at rest to build/screenshots/viewer-*.png.

    python benchmarks/viewer_fps.py                 # the room at 1 cm, ~1.5 M faces
    python benchmarks/viewer_fps.py --quick         # the object at 4 cm, for a smoke run
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: Chromium's software WebGL: ANGLE on SwiftShader (no GPU).
GL_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _wait(c: httpx.Client, job_id: str, timeout: float = 1800) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = c.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("done", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise TimeoutError(f"job {job_id} did not finish in {timeout} s")


def _scene(c: httpx.Client, name: str, views: int, voxel: float) -> tuple[str, dict]:
    from rangefuse.engine.synth import make_dataset

    data = make_dataset(name, views=views)
    body = {"name": f"{name} {voxel * 100:g} cm", "voxel_size": voxel, "mode": "mapping"}
    sid = c.post("/v1/scenes", json=body).raise_for_status().json()["id"]
    for scan_name, scan in data.scans:
        meta = {"name": scan_name, "pose": scan.T_W_S.tolist(), "sensor": scan.sensor.to_dict()}
        files = {"range": ("range.npy", _npy(scan.range_m)), "meta": (None, json.dumps(meta))}
        c.post(f"/v1/scenes/{sid}/scans", files=files).raise_for_status()
    t0 = time.perf_counter()
    job_id = c.post(f"/v1/scenes/{sid}/reconstructions", json={}).json()["job"]["id"]
    job = _wait(c, job_id)
    if job["state"] != "done":
        raise RuntimeError(f"reconstruction {job['state']}: {job.get('error')}")
    job["wall_s"] = time.perf_counter() - t0
    return sid, job


def _measure(page, seconds: float, lod: bool) -> dict:
    """Orbit for ``seconds`` (after a 1 s warm-up: shaders compiled, buffers uploaded);
    ``lod``: draw the coarse level while moving, as the page does when a person drags."""
    js_lod = "true" if lod else "false"
    page.evaluate(f"window.rangefuseViewer.orbit(1, {js_lod})")
    return page.evaluate(f"window.rangefuseViewer.orbit({seconds}, {js_lod})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the object at 4 cm, 1 s orbits")
    parser.add_argument("--views", type=int, default=30, help="room views (more: more faces)")
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=800)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT))
    from playwright.sync_api import sync_playwright

    from tests.test_service import Server

    name, views, voxel, seconds = "room", args.views, args.voxel, args.seconds
    if args.quick:
        name, views, voxel, seconds = "object", 4, 0.04, 1.0
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("viewer_fps: needs Chromium (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        srv = Server(Path(tmp) / "data", max_upload_mb=64).start()
        try:
            token = srv.read_token()
            headers = {"Authorization": f"Bearer {token}"}
            with httpx.Client(base_url=srv.url, headers=headers, timeout=600) as c:
                sid, job = _scene(c, name, views, voxel)
            res = job["result"]
            print(f"{name} at {voxel * 100:g} cm, {views} views: {res['faces']:,} faces, "
                  f"preview {res['preview_faces']:,} faces; reconstruction job "
                  f"{job['wall_s']:.1f} s")  # fmt: skip
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, args=GL_ARGS)
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                gl = page.evaluate(
                    "(() => { const g = document.createElement('canvas').getContext('webgl2');"
                    " const e = g.getExtension('WEBGL_debug_renderer_info');"
                    " return e ? g.getParameter(e.UNMASKED_RENDERER_WEBGL) : 'unknown'; })()"
                )
                t0 = time.perf_counter()
                page.goto(f"{srv.url}/?scene={sid}#token={token}")
                page.wait_for_function("document.querySelector('#status').dataset.full === '0'")
                loads = [time.perf_counter() - t0]
                faces = [int(page.get_attribute("#status", "data-faces"))]
                shots = ROOT / "build" / "screenshots"
                shots.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(shots / f"viewer-{name}-preview.png"))
                runs = [_measure(page, seconds, True), _measure(page, seconds, False)]
                t0 = time.perf_counter()
                page.check("#full-res")
                page.wait_for_function(
                    "document.querySelector('#status').dataset.full === '1'", timeout=600_000
                )
                loads.append(time.perf_counter() - t0)
                faces.append(int(page.get_attribute("#status", "data-faces")))
                page.screenshot(path=str(shots / f"viewer-{name}-full.png"))
                runs += [_measure(page, seconds, True), _measure(page, seconds, False)]
                browser.close()
        finally:
            srv.stop()
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"headless Chromium, {gl}, {args.width}x{args.height}, orbit {seconds:g} s; "
          f"load average after: {load} (2 cores)")  # fmt: skip
    print(f"{'mesh':<9}{'faces':>11}{'load s':>8}  {'while orbiting':<24}{'frames':>7}{'fps':>7}")
    for i, run in enumerate(runs):
        mesh, lod = i // 2, i % 2 == 0
        drawn = f"{'coarse, half res' if lod else 'every face'} {run['faces']:,}"
        print(f"{('preview', 'full')[mesh]:<9}{faces[mesh]:>11,}{loads[mesh]:>8.1f}  "
              f"{drawn:<24}{run['frames']:>7}{run['fps']:>7.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
