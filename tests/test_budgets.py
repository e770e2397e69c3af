"""Resource budgets (engine/budget.py, docs/budgets.md): the cheap estimate of a scan's tiles
against the real allocation, the limits through the real service (uvicorn on loopback, a
real store) and the command line."""

from __future__ import annotations

import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rangefuse.engine import (
    CylindricalSensor,
    FusionParams,
    GridSpec,
    InvalidGridError,
    NoiseModel,
    OrthographicSensor,
    PinholeSensor,
    Scan,
    SphericalSensor,
    prepare_scan,
    tiles_touched,
)
from rangefuse.engine._budget_estimate import rays
from rangefuse.engine.budget import (
    BudgetError,
    Limits,
    SceneTally,
    check_grid,
    check_scans,
    estimate_scan,
    grid_tiles,
)
from rangefuse.engine.grid import KEY_LIMIT, pack_keys
from rangefuse.engine.params import default_eps
from rangefuse.engine.synth import make_dataset, parse_noise
from rangefuse.storage import Store, write_dataset
from rangefuse.storage.archive import ScanArchive

from .test_cli import run_main
from .test_service import _npy, client_of, serving

ROOT = Path(__file__).resolve().parents[1]


def _params(h: float) -> FusionParams:
    return FusionParams(NoiseModel(eps=default_eps(h), rho=0.05))


# --- the estimate against the real allocation --------------------------------------------------

#: Every scan's estimate lies within these factors of the tiles it allocates (measured over
#: the synthetic scenes at 2 mm to 4 cm and tiles of 8 to 32 voxels: 0.63 to 2.1, median
#: about 1; docs/budgets.md).
LOW, HIGH = 0.5, 4.0


@pytest.mark.parametrize(
    ("name", "voxel", "tile"),
    [("object", 0.012, 16), ("object", 0.004, 8), ("room", 0.04, 16), ("room", 0.01, 16),
     ("room", 0.005, 32), ("street", 0.04, 16), ("street", 0.02, 8)],
)  # fmt: skip
def test_the_estimate_is_near_the_real_allocation(datasets, name, voxel, tile):
    grid = GridSpec(voxel, tile, "mapping")
    params = _params(voxel)
    for scan_id, scan in datasets[name].scans:
        actual = len(tiles_touched(prepare_scan(scan, params), grid))
        estimate = estimate_scan(scan, params, grid).tiles
        assert LOW <= estimate / actual <= HIGH, (scan_id, estimate, actual)


def test_noise_dropouts_and_spikes_do_not_throw_the_estimate_off():
    data = make_dataset("room", views=2, noise=parse_noise("gaussian:0.005,dropouts:0.05,"
                                                          "spikes:0.01"))  # fmt: skip
    grid = GridSpec(0.01, 16, "mapping")
    for _, scan in data.scans:
        actual = len(tiles_touched(prepare_scan(scan, _params(0.01)), grid))
        assert LOW <= estimate_scan(scan, _params(0.01), grid).tiles / actual <= HIGH


def test_the_scene_tally_bounds_the_union_of_the_scans(datasets):
    for name, voxel in (("room", 0.02), ("street", 0.04)):
        grid = GridSpec(voxel, 16, "mapping")
        tally = SceneTally(grid)
        keys = []
        for _, scan in datasets[name].scans:
            tally.add(estimate_scan(scan, _params(voxel), grid, with_keys=True))
            keys.append(pack_keys(tiles_touched(prepare_scan(scan, _params(voxel)), grid)))
        union = len(np.unique(np.concatenate(keys)))
        assert LOW <= tally.tiles / union <= HIGH, (name, tally.tiles, union)


def test_closed_mode_estimates_bound_the_allocation(datasets):
    data = datasets["object"]
    grid = GridSpec(0.012, 8, "closed", data.bounds)
    lo, hi = grid.roi_tiles()
    assert grid_tiles(grid) == int(np.prod(hi - lo))
    for _, scan in data.scans:
        estimate = estimate_scan(scan, _params(0.012), grid).tiles
        actual = len(tiles_touched(prepare_scan(scan, _params(0.012)), grid))
        assert actual <= estimate <= grid_tiles(grid)


def test_a_voxel_size_a_thousand_times_too_small_costs_the_same(datasets):
    scan = datasets["room"].scans[0][1]
    times = {}
    for voxel in (0.01, 1e-5, 1e-6):
        grid = GridSpec(voxel, 16, "mapping")
        best = math.inf
        for _ in range(20):
            t0 = time.perf_counter()
            estimate = estimate_scan(scan, _params(voxel), grid)
            best = min(best, time.perf_counter() - t0)
        times[voxel] = best
        if voxel < 1e-4:
            assert estimate.tiles > 10**9  # counted, not enumerated
    # a few milliseconds on a 640 x 480 scan (the bound leaves room for a shared machine)
    assert max(times.values()) < 0.025, times


def test_the_estimate_compiles_nothing(tmp_path):
    # the API process checks uploads with it: not one numba kernel compiled or loaded
    code = """
import gc
from numba.core.dispatcher import Dispatcher
from rangefuse.engine import FusionParams, GridSpec, NoiseModel
from rangefuse.engine.budget import estimate_scan
from rangefuse.engine.synth import make_dataset
scan = make_dataset("street", views=1, length_m=4).scans[0][1]
params = FusionParams(NoiseModel(eps=0.02, rho=0.05))
def compiled():
    return sum(len(d.overloads) for d in gc.get_objects() if isinstance(d, Dispatcher))
n0 = compiled()
estimate_scan(scan, params, GridSpec(0.01, 16, "mapping"), with_keys=True)
estimate_scan(scan, params, GridSpec(0.01, 16, "closed", (-5, -5, -1, 5, 5, 3)))
print(compiled() - n0)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=300, check=True)  # fmt: skip
    assert out.stdout.strip().splitlines()[-1] == "0", out.stdout + out.stderr


def _sensors():
    return [
        PinholeSensor(width=8, height=6, fx=5.0, fy=6.0, cx=3.5, cy=2.5, max_range=9.0,
                      range_convention="z"),
        PinholeSensor(width=8, height=6, fx=5.0, fy=6.0, cx=3.5, cy=2.5, max_range=9.0),
        SphericalSensor(width=8, height=6, el_min=-0.4, el_max=0.3, wrap=True, max_range=9.0),
        SphericalSensor(width=8, height=4, elevations=(0.3, 0.1, -0.2, -0.5), max_range=9.0,
                        az_min=-1.0, az_max=1.0),
        CylindricalSensor(width=8, height=6, fy=4.0, cy=2.5, max_range=9.0),
        CylindricalSensor(width=8, height=6, fy=4.0, cy=2.5, max_range=9.0,
                          range_convention="radial"),
        CylindricalSensor(width=8, height=6, fy=40.0, cy=2.5, max_range=9.0, axial="linear",
                          range_convention="radial"),
        OrthographicSensor(width=8, height=6, sx=0.1, sy=0.2, cx=3.0, cy=2.0, max_range=9.0),
    ]  # fmt: skip


@pytest.mark.parametrize("sensor", _sensors(), ids=lambda s: s.model)
def test_the_numpy_rays_unproject_like_the_kernels(sensor):
    v, u = np.mgrid[0 : sensor.height, 0 : sensor.width].astype(np.float64)
    A, B = rays(sensor, u, v)
    for d in (0.5, 3.0):
        np.testing.assert_allclose(A + d * B, sensor.unproject(u, v, np.full_like(u, d)),
                                   atol=1e-12)  # fmt: skip


# --- the key range and the closed grid ----------------------------------------------------------


def test_bounds_past_the_tile_keys_are_refused_by_the_grid():
    with pytest.raises(InvalidGridError) as info:
        GridSpec(0.01, 16, "closed", (-1e9, -1e9, -1e9, 1e9, 1e9, 1e9))
    assert str(info.value) == (
        "bounds: x0 = -1e+09 m lies beyond the range of tile keys: at voxel size 0.01 m and "
        "tile size 16 a scene spans +-167772 m on each axis (1,048,575 tiles from the origin)"
    )
    edge = (KEY_LIMIT - 1) * 16 * 0.01 - 1.0
    grid = GridSpec(0.01, 16, "mapping", (-edge, -edge, -edge, edge, edge, edge))
    pack_keys(np.stack(grid.roi_tiles()) - [[0, 0, 0], [1, 1, 1]])  # both corners pack


def test_a_scan_beyond_the_tile_keys_is_refused(datasets):
    scan = datasets["object"].scans[0][1]
    T = scan.T_W_S.copy()
    T[0, 3] = 2e5
    far = Scan(range_m=scan.range_m, T_W_S=T, sensor=scan.sensor)
    with pytest.raises(BudgetError, match="^scan: its surface band reaches 2e\\+05 m") as info:
        estimate_scan(far, _params(0.01), GridSpec(0.01, 16, "mapping"))
    assert info.value.limit == "key_range"


def test_a_closed_grid_over_the_budget_is_refused(datasets):
    bounds = datasets["object"].bounds
    check_grid(GridSpec(0.012, 16, "closed", bounds), Limits())
    with pytest.raises(BudgetError) as info:
        check_grid(GridSpec(1.5e-4, 16, "closed", bounds), Limits(knobs={"max_scene_tiles": "K"}))
    assert info.value.limit == "max_scene_tiles" and info.value.allowed == 4_000_000
    assert "over the limit of 4,000,000 tiles per scene (K)" in str(info.value)
    with pytest.raises(BudgetError, match=r"over the limit of 1000 bytes per scene \(B\)"):
        check_grid(
            GridSpec(0.012, 16, "closed", bounds),
            Limits(max_scene_bytes=1000, knobs={"max_scene_bytes": "B"}),
        )


def test_the_datasets_fit_the_default_limits():
    # the synthetic scenes at their documented voxel sizes (README, benchmarks), whole
    for name, voxel, mode in (("room", 0.01, "mapping"), ("object", 0.012, "closed"),
                              ("street", 0.01, "mapping")):  # fmt: skip
        data = make_dataset(name, views=None if name != "room" else 20)
        grid = GridSpec(voxel, 16, mode, data.bounds if mode == "closed" else None)
        check_grid(grid, Limits())
        check_scans(data.scans, _params(voxel), grid, Limits())  # raises past a limit


# --- the service ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from serving(
        tmp_path_factory.mktemp("data"), RANGEFUSE_WORKERS="1",
        RANGEFUSE_MAX_SCENE_TILES="1000", RANGEFUSE_MAX_SCENE_BYTES="16MiB",
        RANGEFUSE_MAX_SCENES_PER_TENANT="8",
    )  # fmt: skip


@pytest.fixture(scope="module")
def client(server):
    with client_of(server, timeout=120) as c:
        yield c


@pytest.fixture(scope="module")
def room():
    return make_dataset("room", views=2)


def _upload(client, scene_id, scan):
    meta = json.dumps({"pose": scan.T_W_S.tolist(), "sensor": scan.sensor.to_dict()})
    files = {"range": ("range.npy", _npy(scan.range_m)), "meta": (None, meta)}
    return client.post(f"/v1/scenes/{scene_id}/scans", files=files)


def _scene(client, **body) -> str:
    r = client.post("/v1/scenes", json={"name": "b", "mode": "mapping", **body})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _nothing_stored(server, client, scene_id) -> None:
    assert client.get(f"/v1/scenes/{scene_id}/scans").json() == []
    archive = ScanArchive(server.data_dir / "scenes" / scene_id / "scene.zarr")
    assert archive.ids() == []
    assert client.get("/healthz").status_code == 200  # and the service answers


def _scene_folders(server) -> set[str]:
    with Store.open(server.data_dir) as store:
        return {row.id for row in store.catalog.scenes()}


def test_a_scan_over_the_tiles_per_scan_is_refused(server, client, room):
    sid = _scene(client, voxel_size=1e-4)
    r = _upload(client, sid, room.scans[0][1])
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert detail.startswith("scan: would allocate about ")
    assert detail.endswith(
        "at voxel size 0.0001 m, over the limit of 1,000,000 tiles per scan "
        "(RANGEFUSE_MAX_SCAN_TILES); a larger voxel size allocates fewer"
    )
    _nothing_stored(server, client, sid)


def test_a_scan_that_takes_the_scene_over_its_tiles_is_refused(server, client, room):
    sid = _scene(client, voxel_size=0.01, tile_size=8)
    r = _upload(client, sid, room.scans[0][1])
    assert r.status_code == 422
    assert r.json()["detail"].startswith("scene: would hold about ")
    assert "over the limit of 1,000 tiles per scene (RANGEFUSE_MAX_SCENE_TILES)" in r.text
    _nothing_stored(server, client, sid)


def test_a_scan_that_takes_the_scene_over_its_bytes_is_refused_with_413(server, client, room):
    sid = _scene(client, voxel_size=0.02, tile_size=32)  # about 100 tiles of 256 KiB
    r = _upload(client, sid, room.scans[0][1])
    assert r.status_code == 413
    assert r.json()["detail"].startswith("scene: would hold about ")
    assert "over the limit of 16 MiB per scene (RANGEFUSE_MAX_SCENE_BYTES)" in r.text
    _nothing_stored(server, client, sid)


def test_a_scan_beyond_the_tile_keys_is_refused_over_http(server, client, room):
    sid = _scene(client, voxel_size=0.001)
    scan = room.scans[0][1]
    T = scan.T_W_S.copy()
    T[0, 3] = 1e5
    r = _upload(client, sid, Scan(range_m=scan.range_m, T_W_S=T, sensor=scan.sensor))
    assert r.status_code == 422
    assert r.json()["detail"].startswith("scan: its surface band reaches 1e+05 m from the")
    _nothing_stored(server, client, sid)


@pytest.mark.parametrize(
    ("body", "start"),
    [
        ({"voxel_size": 1.5e-4, "mode": "closed", "bounds": [-0.5, -0.5, 0, 0.5, 0.5, 1]},
         "bounds: the closed grid's region of interest holds 72,"),
        ({"voxel_size": 0.01, "mode": "closed", "bounds": [-1e9, -1e9, -1e9, 1e9, 1e9, 1e9]},
         "bounds: x0 = -1e+09 m lies beyond the range of tile keys"),
    ],
)  # fmt: skip
def test_scenes_past_the_keys_or_over_the_budget_are_refused(server, client, body, start):
    before = _scene_folders(server)
    r = client.post("/v1/scenes", json={"name": "big", **body})
    assert r.status_code == 422
    assert r.json()["detail"].startswith(start), r.text
    assert _scene_folders(server) == before
    assert client.get("/v1/scenes").status_code == 200


def test_a_scan_within_the_budgets_is_fused_and_the_tenant_limit_holds(server, client, room):
    sid = _scene(client, voxel_size=0.04)
    r = _upload(client, sid, room.scans[0][1])
    assert r.status_code == 202, r.text
    job = r.json()["job"]["id"]
    deadline = time.time() + 240
    while client.get(f"/v1/jobs/{job}").json()["state"] not in ("done", "failed"):
        assert time.time() < deadline
        time.sleep(0.2)
    assert client.get(f"/v1/jobs/{job}").json()["state"] == "done"
    # scenes per tenant: RANGEFUSE_MAX_SCENES_PER_TENANT=8
    have = len(client.get("/v1/scenes").json())
    for _ in range(8 - have):
        _scene(client, voxel_size=0.04)
    r = client.post("/v1/scenes", json={"name": "one too many", "voxel_size": 0.04})
    assert r.status_code == 422
    assert r.json()["detail"] == (
        "scenes: tenant 'default' has 8 scenes, the limit of 8 per tenant "
        "(RANGEFUSE_MAX_SCENES_PER_TENANT); delete one first"
    )
    assert len(client.get("/v1/scenes").json()) == 8


# --- the command line ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room_folder(tmp_path_factory, room):
    data = room
    return write_dataset(tmp_path_factory.mktemp("room") / "room", data.sensor, data.scans)


def test_fuse_refuses_a_tiny_voxel_at_once(room_folder, capsys):
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    code, out, err = run_main(["fuse", room_folder, "--voxel-size", "0.0001"], capsys)
    elapsed = time.perf_counter() - t0
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("rangefuse fuse: error: scan scan_0000: would allocate about ")
    assert lines[0].endswith(
        "over the limit of 1,000,000 tiles per scan (--max-scan-tiles); a larger voxel size "
        "allocates fewer"
    )
    assert elapsed < 30, elapsed  # refused before any fusion (not a timing test: 0.25 s here)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss < 200_000  # KiB


def test_fuse_options_raise_and_lower_the_limits(room_folder, capsys, tmp_path):
    code, _, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.04", "--max-scan-tiles", "10"], capsys
    )
    assert code == 2 and "over the limit of 10 tiles per scan (--max-scan-tiles)" in err
    code, _, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.04", "--max-scene-bytes", "1MiB"], capsys
    )
    assert code == 2 and "over the limit of 1 MiB per scene (--max-scene-bytes)" in err
    code, _, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.04", "--max-scene-bytes", "lots"], capsys
    )
    assert code == 2 and "not a size such as 64GiB or a number of bytes: 'lots'" in err
    code, _, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.01", "--mode", "closed", "--quiet",
         "--max-scene-tiles", "100"], capsys,
    )  # fmt: skip
    assert code == 2
    assert "bounds: the closed grid's region of interest holds " in err
    assert "over the limit of 100 tiles per scene (--max-scene-tiles)" in err
    store = tmp_path / "store"
    code, _, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.0001", "--store", store], capsys
    )
    assert code == 2 and "(--max-scan-tiles)" in err
    assert not store.exists()  # refused before the store is created
    code, out, err = run_main(
        ["fuse", room_folder, "--voxel-size", "0.04", "--quiet", "--max-scan-tiles", "5000"],
        capsys,
    )
    assert code == 0, err
    assert out.startswith("fused 2 scans into ")


def test_add_checks_the_store_scene_before_storing(room, capsys, tmp_path):
    one = write_dataset(tmp_path / "one", room.sensor, room.scans[:1])
    other = write_dataset(tmp_path / "other", room.sensor, room.scans[1:])
    store = tmp_path / "store"
    first = ["fuse", one, "--voxel-size", "0.04", "--store", store, "--quiet"]
    assert run_main(first, capsys)[0] == 0
    with Store.open(store) as s:
        scene_id = s.catalog.scenes()[0].id
        tiles = s.catalog.n_tiles(scene_id)
    scan = next((other / "scans").glob("*.npz"))
    code, out, err = run_main(["add", store, scan, "--max-scene-tiles", str(tiles)], capsys)
    assert code == 2, out
    assert err.startswith("rangefuse add: error: scene: would hold about ")
    assert f"about {tiles:,} of them there already" in err and "(--max-scene-tiles)" in err
    with Store.open(store) as s:
        assert len(s.catalog.scans(scene_id)) == 1
    code, out, err = run_main(["add", store, scan, "--quiet"], capsys)
    assert code == 0, err
