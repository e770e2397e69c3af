"""/docs and /redoc without internet: Swagger UI and ReDoc are served from the copies in
``service/static/vendor`` (installed with the package), never from a CDN.

The service runs under a real uvicorn on loopback (in a thread, without the lifespan: the
docs need no Dask cluster); the rendering check drives headless Chromium over the DevTools
protocol with every host name but 127.0.0.1 unresolvable, and records every URL it asked for.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from typing import Any

import httpx
import pytest
import uvicorn

from tests.test_service import ROOT, _free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
VENDOR = ROOT / "service" / "static" / "vendor"
#: What the pages load, and the licences that travel with them.
VENDORED = [
    "swagger-ui/swagger-ui-bundle.js", "swagger-ui/swagger-ui.css", "swagger-ui/favicon-32x32.png",
    "swagger-ui/LICENSE", "swagger-ui/NOTICE", "swagger-ui/swagger-ui-bundle.js.LICENSE.txt",
    "redoc/redoc.standalone.js", "redoc/LICENSE", "redoc/redoc.standalone.js.LICENSE.txt",
    "three/three.module.js", "three/three.core.js", "three/OrbitControls.js", "three/LICENSE",
]  # fmt: skip
_ASSET = re.compile(r"""\b(?:src|href)\s*=\s*["']([^"']+)["']""", re.IGNORECASE)


class Browser:
    """Headless Chromium over the DevTools protocol (``websockets``): open a page, evaluate
    JavaScript in it, and list every URL it requested. With ``offline``, host names other
    than 127.0.0.1 do not resolve (the network is closed to the page)."""

    def __init__(self, offline: bool = True) -> None:
        from websockets.sync.client import connect

        self._profile = tempfile.mkdtemp(prefix="rangefuse-chromium-")
        args = [
            CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
            "--no-first-run", "--remote-debugging-port=0", f"--user-data-dir={self._profile}",
        ]  # fmt: skip
        if offline:
            args.append("--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1")
        self._proc = subprocess.Popen(  # its own process group: close() ends every child
            [*args, "about:blank"],
            stderr=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        ws_url = None
        deadline = time.time() + 60
        assert self._proc.stderr is not None
        while ws_url is None and time.time() < deadline:
            line = self._proc.stderr.readline()
            if not line and self._proc.poll() is not None:
                break
            found = re.search(r"DevTools listening on (ws://\S+)", line)
            ws_url = found.group(1) if found else None
        assert ws_url, "Chromium did not start its DevTools endpoint"
        threading.Thread(target=self._proc.stderr.read, daemon=True).start()  # keep it drained
        self._connection = contextlib.ExitStack()
        self._ws = self._connection.enter_context(connect(ws_url, max_size=None, open_timeout=30))
        self._next_id = 0
        self.requested: list[str] = []
        target = self._call("Target.createTarget", {"url": "about:blank"})["targetId"]
        attached = self._call("Target.attachToTarget", {"targetId": target, "flatten": True})
        self._session = attached["sessionId"]
        self._call("Network.enable", session=True)
        self._call("Page.enable", session=True)

    def _call(self, method: str, params: dict | None = None, session: bool = False) -> Any:
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self._session
        self._ws.send(json.dumps(message))
        while True:
            answer = json.loads(self._ws.recv(timeout=60))
            if answer.get("method") == "Network.requestWillBeSent":
                self.requested.append(answer["params"]["request"]["url"])
            if answer.get("id") == self._next_id:
                assert "error" not in answer, answer["error"]
                return answer.get("result", {})

    def open(self, url: str) -> None:
        self._call("Page.navigate", {"url": url}, session=True)

    def evaluate(self, expression: str) -> Any:
        result = self._call(
            "Runtime.evaluate", {"expression": expression, "returnByValue": True}, session=True
        )
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60.0) -> Any:
        """The value of ``expression`` once it is truthy (polled every 0.1 s)."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.1)
        raise AssertionError(f"not true within {timeout:g} s: {expression}")

    def close(self) -> None:
        """Close Chromium and remove its profile. Chromium's helper processes outlive the
        browser process by a moment and may still write into the profile (CI once failed on
        ``Directory not empty: 'Default'``), so the whole process group is ended and the
        removal retried until it holds."""
        with contextlib.suppress(Exception):  # ask politely; the answer is not awaited
            self._ws.send(json.dumps({"id": 0, "method": "Browser.close"}))
        self._connection.close()
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.terminate()
            self._proc.wait(timeout=30)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self._proc.pid, signal.SIGKILL)
        deadline = time.time() + 30
        while True:
            try:
                shutil.rmtree(self._profile)
                break
            except FileNotFoundError:
                break
            except OSError:
                if time.time() > deadline:
                    raise
                time.sleep(0.2)


@pytest.fixture(scope="module")
def docs_url(tmp_path_factory):
    """A real uvicorn on loopback serving the app (lifespan off: no cluster needed)."""
    from rangefuse.service.app import create_app
    from rangefuse.service.settings import Settings

    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("store")))
    port = _free_port()
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, lifespan="off", log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not server.started and time.time() < deadline:
        time.sleep(0.05)
    assert server.started
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=30)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_only_local_assets(docs_url, page):
    html = httpx.get(docs_url + page)
    assert html.status_code == 200 and "/openapi.json" in html.text
    assets = _ASSET.findall(html.text)
    assert assets, html.text
    assert not re.search(r"https?://", html.text), "an absolute URL in " + page
    for asset in assets:
        assert asset.startswith("/static/vendor/"), asset
        r = httpx.get(docs_url + asset)
        assert r.status_code == 200 and r.content == (VENDOR / asset[15:]).read_bytes(), asset
    # the script each page runs is the vendored one
    script = "swagger-ui-bundle.js" if page == "/docs" else "redoc.standalone.js"
    assert any(a.endswith(script) for a in assets)
    assert httpx.get(docs_url + "/openapi.json").json()["info"]["title"] == "rangefuse"


def test_unknown_vendor_files_are_404_and_the_service_answers(docs_url):
    for path in ("/static/vendor/nope.js", "/static/vendor/../../app.py", "/static/index.html"):
        assert httpx.get(docs_url + path).status_code == 404, path
    assert httpx.get(docs_url + "/docs").status_code == 200


def test_the_vendored_files_and_their_licences_are_there():
    present = sorted(str(p.relative_to(VENDOR)) for p in VENDOR.glob("*/*"))
    assert present == sorted(VENDORED)
    assert "Apache License" in (VENDOR / "swagger-ui" / "LICENSE").read_text()
    assert "MIT License" in (VENDOR / "redoc" / "LICENSE").read_text()
    assert "MIT License" in (VENDOR / "three" / "LICENSE").read_text()


def test_a_wheel_built_from_the_repository_holds_the_assets(tmp_path):
    """Built from a copy (setuptools writes build/ beside the sources); pip fetches the
    build backend (setuptools, wheel) as pyproject.toml asks."""
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(ROOT / "pyproject.toml", src)
    shutil.copy(ROOT / "README.md", src)
    for package in ("engine", "storage", "service"):
        shutil.copytree(ROOT / package, src / package, ignore=shutil.ignore_patterns("__pycache__"))
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "dist"),
         str(src)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("rangefuse-*.whl")
    with zipfile.ZipFile(wheel) as z:
        for name in VENDORED:
            data = z.read(f"rangefuse/service/static/vendor/{name}")
            assert data == (VENDOR / name).read_bytes(), name
        assert "rangefuse/service/static/index.html" in z.namelist()
        assert "rangefuse/service/static/app/app.js" in z.namelist()  # the web page's code


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (.ci/run installs it)")
def test_docs_render_with_the_network_closed(docs_url):
    browser = Browser(offline=True)
    try:
        browser.open(docs_url + "/docs")
        paths = browser.wait_for(
            "Array.from(document.querySelectorAll('.opblock-summary-path'))"
            ".map(e => e.getAttribute('data-path'))"
        )
        assert "/v1/scenes" in paths and "/v1/scenes/{scene_id}/scans" in paths
        assert "/healthz" in paths and "/metrics" in paths
        browser.open(docs_url + "/redoc")
        text = browser.wait_for(
            "document.querySelector('[data-section-id^=\"operation/\"]') && document.body.innerText"
        )
        assert "/v1/scenes/{scene_id}/scans" in text
        local = (docs_url, f"blob:{docs_url}", "about:", "data:")  # blob: ReDoc's worker
        outside = [u for u in browser.requested if not u.startswith(local)]
        assert outside == [], outside
        assert f"{docs_url}/static/vendor/swagger-ui/swagger-ui-bundle.js" in browser.requested
    finally:
        browser.close()
