"""Scans and meshes over the API (issue 20, part 3): a scene's default sensor, given at its
creation or taken from its first scan, that later uploads may leave out; a scan named after
its file; downloads named after the scene; far_ranges in the scan listing; and a catalog
written before these columns existed still opens."""

from __future__ import annotations

import io
import json
import sqlite3

import numpy as np
import pytest
from rangefuse.engine.synth import make_dataset
from rangefuse.storage.catalog import Catalog

from tests.test_service import _npy, _scene_body, _upload, _wait, client_of, serving


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def client(server):
    with client_of(server) as c:
        yield c


@pytest.fixture(scope="module")
def data():
    return make_dataset("object", views=3)


def _pose_only(scan) -> str:
    return json.dumps({"pose": scan.T_W_S.tolist()})


def _npz_without_sensor(scan) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, range=scan.range_m, pose=scan.T_W_S)
    return buf.getvalue()


def test_a_scene_created_with_a_sensor_takes_uploads_without_one(client, data):
    (_, first), (_, second), _ = data.scans
    body = _scene_body(data, name="with sensor", sensor=first.sensor.to_dict())
    r = client.post("/v1/scenes", json=body)
    assert r.status_code == 201, r.text
    scene = r.json()
    assert scene["sensor"] == first.sensor.to_dict()
    assert client.get(f"/v1/scenes/{scene['id']}").json()["sensor"] == first.sensor.to_dict()
    r = _upload(client, scene["id"], _npy(first.range_m), _pose_only(first), filename="a.npy")
    assert r.status_code == 202, r.text
    r = _upload(client, scene["id"], _npz_without_sensor(second), "{}", filename="b.npz")
    assert r.status_code == 202, r.text
    assert _wait(client, r.json()["job"]["id"])["state"] == "done"
    scans = client.get(f"/v1/scenes/{scene['id']}/scans").json()
    assert [s["state"] for s in scans] == ["fused", "fused"]


def test_the_first_upload_gives_a_scene_its_sensor(client, data):
    (_, first), (_, second), _ = data.scans
    sid = client.post("/v1/scenes", json=_scene_body(data)).json()["id"]
    assert client.get(f"/v1/scenes/{sid}").json()["sensor"] is None
    # no sensor anywhere: the message speaks of the upload's meta and the scene's sensor
    r = _upload(client, sid, _npy(first.range_m), _pose_only(first))
    assert r.status_code == 400
    assert r.json()["detail"].startswith("meta.sensor: missing, and the scene has no sensor")
    r = _upload(client, sid, _npz_without_sensor(first), "{}", filename="a.npz")
    assert r.status_code == 400
    detail = r.json()["detail"]
    assert "no meta.sensor in the upload" in detail and "the scene has no sensor" in detail
    assert "sensor.json" not in detail and "dataset" not in detail
    # the first scan that has one gives it to the scene; the next may leave it out
    meta = json.dumps({"pose": first.T_W_S.tolist(), "sensor": first.sensor.to_dict()})
    assert _upload(client, sid, _npy(first.range_m), meta).status_code == 202
    assert client.get(f"/v1/scenes/{sid}").json()["sensor"] == first.sensor.to_dict()
    r = _upload(client, sid, _npy(second.range_m), _pose_only(second))
    assert r.status_code == 202, r.text


def test_a_bad_scene_sensor_is_refused_with_its_field(client, data):
    sensor = data.scans[0][1].sensor.to_dict()
    for bad, words in (
        ({**sensor, "fx": -5}, "sensor.fx"),
        ({**sensor, "model": "fisheye"}, "unknown sensor model"),
        ({**sensor, "colour": 1}, "sensor.colour"),
    ):
        r = client.post("/v1/scenes", json=_scene_body(data, sensor=bad))
        assert r.status_code == 422, r.text
        assert words in r.json()["detail"]


def test_a_scan_is_named_after_its_file_unless_named(client, data):
    (_, first), (_, second), (_, third) = data.scans
    sid = client.post("/v1/scenes", json=_scene_body(data, sensor=first.sensor.to_dict())).json()[
        "id"
    ]
    r = _upload(client, sid, _npy(first.range_m), _pose_only(first), filename="kitchen_007.npy")
    assert r.json()["scan"]["name"] == "kitchen_007"
    meta = json.dumps({"pose": second.T_W_S.tolist(), "name": "given"})
    r = _upload(client, sid, _npy(second.range_m), meta, filename="ignored.npy")
    assert r.json()["scan"]["name"] == "given"
    r = _upload(client, sid, _npy(third.range_m), _pose_only(third), filename="C:\\scans\\x.y.npy")
    assert r.json()["scan"]["name"] == "x.y"
    names = [s["name"] for s in client.get(f"/v1/scenes/{sid}/scans").json()]
    assert names == ["kitchen_007", "given", "x.y"]


def test_far_ranges_are_listed_with_the_scan(client, data):
    _, scan = data.scans[0]
    sid = client.post("/v1/scenes", json=_scene_body(data, sensor=scan.sensor.to_dict())).json()[
        "id"
    ]
    far = scan.range_m.copy()
    rows, cols = np.nonzero(np.isfinite(far))
    far[rows[:25], cols[:25]] = scan.sensor.max_range + 1.0
    r = _upload(client, sid, _npy(far), _pose_only(scan))
    assert r.status_code == 202, r.text
    assert r.json()["scan"]["far_ranges"] == 25
    (listed,) = client.get(f"/v1/scenes/{sid}/scans").json()
    assert listed["far_ranges"] == 25
    one = client.get(f"/v1/scenes/{sid}/scans/{listed['id']}").json()
    assert one["far_ranges"] == 25


def test_a_download_is_named_after_the_scene(client, data):
    _, scan = data.scans[0]
    body = _scene_body(data, name="Kitchen #2 / ground floor", sensor=scan.sensor.to_dict())
    sid = client.post("/v1/scenes", json=body).json()["id"]
    r = _upload(client, sid, _npy(scan.range_m), _pose_only(scan))
    job = client.post(f"/v1/scenes/{sid}/reconstructions", json={"refine": False}).json()["job"]
    assert _wait(client, job["id"])["state"] == "done"
    for fmt in ("ply", "obj", "glb", "stl"):
        r = client.get(f"/v1/scenes/{sid}/mesh", params={"format": fmt})
        assert r.status_code == 200
        assert r.headers["content-disposition"] == (
            f'attachment; filename="Kitchen_2_ground_floor.{fmt}"'
        )
    # nothing usable left of the name: the scene's id
    sid = client.post("/v1/scenes", json=_scene_body(data, name="###")).json()["id"]
    meta = json.dumps({"pose": scan.T_W_S.tolist(), "sensor": scan.sensor.to_dict()})
    r = _upload(client, sid, _npy(scan.range_m), meta)
    assert r.status_code == 202, r.text
    job = client.post(f"/v1/scenes/{sid}/reconstructions", json={"refine": False}).json()["job"]
    assert _wait(client, job["id"])["state"] == "done"
    r = client.get(f"/v1/scenes/{sid}/mesh")
    assert r.headers["content-disposition"] == f'attachment; filename="{sid}.ply"'


def test_a_catalog_written_before_the_new_columns_opens(tmp_path):
    path = tmp_path / "catalog.sqlite"
    db = sqlite3.connect(path)
    db.executescript(
        """
        CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
        INSERT INTO meta VALUES('version', '1');
        CREATE TABLE scenes(
            id TEXT PRIMARY KEY, name TEXT NOT NULL, tenant TEXT NOT NULL,
            grid TEXT NOT NULL, params TEXT NOT NULL, created_at REAL NOT NULL);
        CREATE TABLE scans(
            scene_id TEXT NOT NULL, id TEXT NOT NULL, seq INTEGER NOT NULL, name TEXT,
            state TEXT NOT NULL, ox REAL NOT NULL, oy REAL NOT NULL, oz REAL NOT NULL,
            reach_m REAL NOT NULL, checksum TEXT NOT NULL, created_at REAL NOT NULL,
            PRIMARY KEY(scene_id, id));
        INSERT INTO scenes VALUES('s1', 'old', 't', '{}', '{}', 1.0);
        INSERT INTO scans VALUES('s1', 'a', 1, NULL, 'fused', 0, 0, 0, 1.0, 'c', 2.0);
        """
    )
    db.commit()
    db.close()
    catalog = Catalog(path)
    try:
        assert catalog.scene("s1").sensor is None
        assert catalog.scan("s1", "a").far_ranges is None
        assert catalog.set_scene_sensor("s1", {"model": "x"}, only_if_none=True)
        assert not catalog.set_scene_sensor("s1", {"model": "y"}, only_if_none=True)
        assert catalog.scene("s1").sensor == {"model": "x"}
        catalog.add_scan("s1", "b", "b", (0, 0, 0), 1.0, "c", far_ranges=3)
        assert catalog.scan("s1", "b").far_ranges == 3
    finally:
        catalog.close()
    Catalog(path).close()  # opened again: the columns are there already
