"""The web page at / in a real browser (headless Chromium): scenes, jobs, the mesh viewer."""

from __future__ import annotations

import shutil
import subprocess

import httpx
import pytest

from tests.test_service import Server, _meta, _npy, _scene_body, _upload, _wait

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _dom(url: str) -> str:
    out = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         "--virtual-time-budget=15000", "--dump-dom", url],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (.ci/run installs it)")
def test_page_lists_scenes_and_jobs_and_shows_the_mesh(tmp_path):
    from rangefuse.engine.synth import make_dataset

    data = make_dataset("object", views=3)
    srv = Server(tmp_path / "data").start()
    try:
        token = srv.read_token()
        with httpx.Client(
            base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60
        ) as c:
            page = httpx.get(f"{srv.url}/")
            assert page.status_code == 200 and "rangefuse" in page.text
            sid = c.post("/v1/scenes", json=_scene_body(data, name="teapot-desk")).json()["id"]
            for _, scan in data.scans:
                assert _upload(c, sid, _npy(scan.range_m), _meta(scan)).status_code == 202
            job = c.post(f"/v1/scenes/{sid}/reconstructions", json={}).json()["job"]["id"]
            assert _wait(c, job)["state"] == "done"
            faces = c.get(f"/v1/jobs/{job}").json()["result"]["faces"]
            listed = c.get("/v1/jobs").json()
            assert listed[0]["id"] == job and all(j["state"] == "done" for j in listed)
        dom = _dom(f"{srv.url}/?scene={sid}#token={token}")  # the fragment never leaves the browser
        assert "teapot-desk" in dom
        assert f'data-job="{job}" data-state="done"' in dom
        assert f'data-triangles="{faces}"' in dom
        # without a token the page still loads and asks for one; the API refuses
        assert "API token" in _dom(f"{srv.url}/")
    finally:
        srv.stop()
