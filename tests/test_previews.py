"""Preview meshes (service/previews.py): simplification that keeps inferred faces apart, the
file format, and the endpoints the page reads (preview, placements)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh
from rangefuse.service import previews

from tests.test_service import _meta, _npy, _scene_body, _upload, _wait, client_of, serving


def _levels(payload: bytes) -> list[tuple[np.ndarray, np.ndarray, int, int]]:
    """The levels of a preview file: (positions, indices, n_measured, source_faces)."""
    out, o = [], 0
    while o < len(payload):
        magic, nv, nf, nm, src = struct.unpack_from("<8s4I", payload, o)
        assert magic == b"RFPV0001"
        pos = np.frombuffer(payload, "<f4", nv * 3, o + 24).reshape(-1, 3)
        idx = np.frombuffer(payload, "<u4", nf * 3, o + 24 + nv * 12).reshape(-1, 3)
        out.append((pos, idx, nm, src))
        o += 24 + nv * 12 + nf * 12
    assert o == len(payload)
    return out


def _sphere(subdivisions: int = 6):
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    inferred = s.triangles_center[:, 2] < -0.3  # a cap: the "inferred" part
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int64), inferred


def test_the_preview_keeps_measured_and_inferred_faces_apart():
    v, f, inferred = _sphere()  # 81,920 faces
    payload = previews.preview_of(v, f, inferred, max_faces=20_000, coarse_faces=5_000)
    (pos, idx, nm, src), (cpos, cidx, cnm, csrc) = _levels(payload)
    assert src == csrc == len(f)
    assert len(idx) <= 20_000 and len(cidx) <= 5_000
    share = inferred.mean()
    assert abs((len(idx) - nm) / len(idx) - share) < 0.05  # each part keeps its share
    assert abs((len(cidx) - cnm) / len(cidx) - share) < 0.05
    assert idx.max() < len(pos) and cidx.max() < len(cpos)
    # every measured face lies where measured faces were (z >= -0.3), every inferred one below
    centres = pos[idx].mean(axis=1)
    assert (centres[:nm, 2] > -0.35).all() and (centres[nm:, 2] < -0.25).all()
    radius = np.linalg.norm(pos, axis=1)
    assert np.abs(radius - 1).max() < 0.05  # still the unit sphere


def test_a_small_mesh_is_sent_whole_in_one_level():
    v, f, inferred = _sphere(3)  # 1,280 faces
    ((pos, idx, nm, src),) = _levels(previews.preview_of(v, f, inferred))
    assert len(idx) == src == len(f) and nm == int((~inferred).sum())
    # the same triangles, measured first
    want = np.sort(v[f[~inferred]].reshape(-1, 9), axis=0)
    assert np.array_equal(np.sort(pos[idx[:nm]].reshape(-1, 9), axis=0), want)


def test_vertex_clustering_reduces_big_meshes_and_keeps_the_flags():
    v, f, inferred = _sphere(6)
    cv, cf, ci = previews.cluster_vertices(v, f, inferred, 10_000)
    assert 3_000 < len(cf) < 30_000 and len(ci) == len(cf)
    centres = cv[cf].mean(axis=1)
    assert (centres[ci, 2] < -0.2).all() and (centres[~ci, 2] > -0.4).all()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(tmp_path_factory.mktemp("data"))


def test_preview_and_placements_endpoints(server):
    from rangefuse.engine.synth import make_dataset

    data = make_dataset("object", views=3)
    with client_of(server) as c:
        sid = c.post("/v1/scenes", json=_scene_body(data, name="previewed")).json()["id"]
        r = c.get(f"/v1/scenes/{sid}/preview")
        assert r.status_code == 409 and "reconstruct it first" in r.json()["detail"]
        assert c.get(f"/v1/scenes/{sid}/placements").json() == []
        for _, scan in data.scans:
            assert _upload(c, sid, _npy(scan.range_m), _meta(scan)).status_code == 202
        job = c.post(f"/v1/scenes/{sid}/reconstructions", json={}).json()["job"]["id"]
        result = _wait(c, job)["result"]
        r = c.get(f"/v1/scenes/{sid}/preview")
        assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
        (_, idx, _, src), *_ = _levels(r.content)
        assert src == result["faces"] and len(idx) == result["preview_faces"]
        again = c.get(f"/v1/scenes/{sid}/preview", headers={"If-None-Match": r.headers["etag"]})
        assert again.status_code == 304
        placed = c.get(f"/v1/scenes/{sid}/placements").json()
        assert len(placed) == 3
        for p, (_, scan) in zip(placed, data.scans, strict=True):
            assert np.allclose(p["pose"], scan.T_W_S)
            assert p["sensor"] == json.loads(json.dumps(scan.sensor.to_dict()))
        assert c.get("/v1/scenes/nope/preview").status_code == 404
