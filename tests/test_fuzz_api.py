"""A bounded schemathesis campaign against the live service (issue 19, part 9).

A real ``rangefuse serve`` holds a scene with fused scans and a mesh; schemathesis generates
requests for every operation of the OpenAPI document (its examples, boundary values and
random data; real ids part of the time, from dictionaries) and checks that no answer is a
5xx and that every answer has a documented status code, content type and schema. The
campaign is seeded and bounded; the number of requests it made is printed.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.test_service import Server, _meta, _npy, _wait

pytestmark = pytest.mark.skipif(
    shutil.which("schemathesis", path=str(Path(sys.executable).parent)) is None,
    reason="schemathesis is in the dev extra",
)


def _toml_list(values: list[str]) -> str:
    return "[" + ", ".join(json.dumps(v) for v in values) + "]"


def test_schemathesis_finds_no_server_error_and_no_schema_violation(tmp_path):
    from rangefuse.engine.synth import make_dataset

    server = Server(tmp_path / "data").start()
    try:
        token = server.read_token()
        client = httpx.Client(
            base_url=server.url, headers={"Authorization": f"Bearer {token}"}, timeout=60
        )
        body = {"name": "fuzz", "voxel_size": 0.04, "mode": "mapping"}
        scene = client.post("/v1/scenes", json=body).json()["id"]
        data = make_dataset("object", views=3)
        scans, jobs = [], []
        for _, scan in data.scans:
            files = {"range": ("range.npy", _npy(scan.range_m)), "meta": (None, _meta(scan))}
            r = client.post(f"/v1/scenes/{scene}/scans", files=files)
            assert r.status_code == 202, r.text
            scans.append(r.json()["scan"]["id"])
            jobs.append(r.json()["job"]["id"])
        r = client.post(f"/v1/scenes/{scene}/reconstructions")
        jobs.append(r.json()["job"]["id"])
        assert _wait(client, jobs[-1])["state"] == "done"
        config = tmp_path / "schemathesis.toml"
        config.write_text(
            f'headers = {{ Authorization = "Bearer {token}" }}\n'
            "[dictionaries.scenes]\n"
            f"values = {_toml_list([scene])}\n"
            "[dictionaries.scans]\n"
            f"values = {_toml_list(scans)}\n"
            "[dictionaries.jobs]\n"
            f"values = {_toml_list(sorted(set(jobs)))}\n"
            "[parameters]\n"
            '"path.scene_id" = { dictionary = "scenes", probability = 0.7 }\n'
            '"path.scan_id" = { dictionary = "scans", probability = 0.7 }\n'
            '"path.job_id" = { dictionary = "jobs", probability = 0.7 }\n'
        )
        out = subprocess.run(
            [
                str(Path(sys.executable).parent / "schemathesis"),
                "--config-file", str(config),
                "run", f"{server.url}/openapi.json",
                "--checks", "not_a_server_error,status_code_conformance,"
                "content_type_conformance,response_schema_conformance",
                "--phases", "examples,coverage,fuzzing",
                "--max-examples", "25", "--seed", "19", "--workers", "1",
                "--request-timeout", "30",
            ],
            capture_output=True, text=True, timeout=900, cwd=tmp_path,
        )  # fmt: skip
        report = out.stdout[-6000:]
        made = re.search(r"(\d+) generated", out.stdout)
        print(f"schemathesis: {made.group(1) if made else '?'} test cases")
        assert out.returncode == 0, report
        assert made is not None and int(made.group(1)) > 300, report
        # the service still answers, and logged no traceback
        assert httpx.get(f"{server.url}/healthz", timeout=10).status_code == 200
        assert not any("Traceback" in line for line in server.lines), "".join(server.lines)
    finally:
        server.stop()
