"""LiDAR at city scale (issue 21): the elevation table's index finds the rows a binary search
finds, and a street fused by a volume is the same whether a scan tests every tile or only
those its sphere reaches."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, SphericalSensor, Volume
from rangefuse.engine import _sensor_kernels as _k
from rangefuse.engine._parts import BAND_FREE, BAND_NOTHING, BAND_UNSURE, _band_outcome
from rangefuse.engine._sampling import bilinear, quad_columns, quad_index, quad_origin
from rangefuse.engine.certainty import SHAPE_LINEAR, contribution, logit, quantise
from rangefuse.engine.classify import OUT, classify_tiles
from rangefuse.engine.planner import Sphere, tiles_near
from rangefuse.engine.synth import make_dataset


@njit(cache=True)
def _row_by_bisection(table, n, el):
    # the search the index replaced, written out as it was
    if el >= table[0]:
        v0 = 0
    elif el <= table[n - 1]:
        v0 = n - 2
    else:
        lo = 0
        hi = n - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if table[mid] >= el:
                lo = mid
            else:
                hi = mid
        v0 = lo
    return v0 + (table[v0] - el) / (table[v0] - table[v0 + 1])


@njit(cache=True)
def _rows(table, n, els, out, reference):
    for m in range(els.shape[0]):
        if reference:
            out[m] = _row_by_bisection(table, n, els[m])
        else:
            out[m] = _k._row_from_table(table, n, els[m])


@pytest.mark.parametrize("seed", range(5))
def test_the_table_index_gives_the_rows_of_a_binary_search(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 130))
    # uneven spacing, clusters of close beams included
    steps = rng.exponential(1.0, n - 1) ** 2 + 1e-6
    e = 0.3 - np.concatenate([[0.0], np.cumsum(steps)]) * (0.7 / steps.sum())
    table = _k.elevation_table(e)
    els = np.concatenate([
        rng.uniform(e[-1] - 0.1, e[0] + 0.1, 20000),
        e, np.nextafter(e, np.inf), np.nextafter(e, -np.inf), [math.nan],
    ])  # fmt: skip
    got = np.empty(len(els))
    want = np.empty(len(els))
    _rows(table, n, els, got, False)
    _rows(table, n, els, want, True)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(got.view(np.int64)[:-1], want.view(np.int64)[:-1])  # bit for bit


@njit(cache=True)
def _rows_two_ways(kind, params, table, tans, ts, rhos, start, out):
    # per (t, rho): the quad row project_point's v gives (-1 outside the image) and the one
    # row_of_tangent gives from z / rho as the kernel computes it
    for m in range(ts.shape[0]):
        rho = rhos[m]
        z = ts[m] * rho
        u, v, _ = _k.spherical_in_column(params, table, 0.5, rho, z)
        q = quad_index(kind, params, u, v)
        out[m, 0] = -1 if q < 0 else q // quad_columns(kind, params)
        out[m, 1] = _k.row_of_tangent(tans, z / rho, start[m])


@pytest.mark.parametrize("rows", ["table", "even"])
def test_a_level_columns_rows_from_tangents_are_those_of_atan2(rows: str) -> None:
    """The kernel puts a level column's voxels in their quad rows by the tangent of their
    elevation: where it answers, the row (or 'outside') is the one ``project_point`` gives,
    also a few ulps and a few margins from every row's edge; within the margin it answers
    'unsure' (and the voxel takes ``atan2``)."""
    rng = np.random.default_rng(7)
    e = make_dataset("street", length_m=8).scans[0][1].sensor.elevations
    if rows == "table":
        sensor = SphericalSensor(width=16, height=len(e), max_range=80.0, elevations=e)
    else:
        sensor = SphericalSensor(width=16, height=len(e), max_range=80.0, el_min=e[-1], el_max=e[0])
    kind, params, table = sensor.kernel_args()
    tans = _k.row_tangents(params, table)
    assert len(tans) == len(e) and np.all(np.diff(tans) < 0)
    steps = (-3, -1.5, -0.5, 0.5, 1.5, 3)
    edges = np.concatenate([tans * (1 + f * _k.ROW_TAN_MARGIN) for f in steps])
    near = [np.nextafter(tans, np.inf), np.nextafter(tans, -np.inf), tans, edges]
    ts = np.concatenate([rng.uniform(tans[-1] - 0.2, tans[0] + 0.2, 20000), *near, [0.0, -0.0]])
    ts = np.repeat(ts, 3)
    rhos = np.tile([0.7, 13.0, 79.0], len(ts) // 3)
    start = rng.integers(-2, len(e) + 2, len(ts))
    out = np.empty((len(ts), 2), np.int64)
    _rows_two_ways(kind, params, table, tans, ts, rhos, start, out)
    sure = out[:, 1] != _k.ROW_UNSURE
    assert np.array_equal(out[sure, 1], out[sure, 0])
    assert (out[sure, 1] == _k.ROW_OUTSIDE).sum() > 100 and (out[sure, 1] >= 0).sum() > 10000
    assert 0 < (~sure).sum() < 0.1 * len(ts)  # the edges' own tangents and those within 1e-9
    assert not (~sure[: 3 * 20000]).any()  # random ones are not that near an edge


@njit(cache=True)
def _columns_two_ways(params, edges, wrap, xs, ys, start, out):
    # per direction: the quad column project_point's u gives (-1 outside the image) and the
    # one column_of_direction gives, walking from ``start``
    for m in range(xs.shape[0]):
        x = xs[m]
        y = ys[m]
        u, rho = _k.spherical_column(params, x, y)
        out[m, 0] = quad_index(_k.SPHERICAL, params, u, 0.0)
        out[m, 1] = _k.column_of_direction(edges, x, y, rho, start[m], wrap)


@pytest.mark.parametrize(("W", "wrap"), [(1024, True), (16, True), (64, False)])
def test_a_tilted_voxels_column_from_its_direction_is_that_of_atan2(W: int, wrap: bool) -> None:
    """A tilted pose's voxel finds its quad column from its direction against the columns'
    edges: where the answer is sure it is the column ``project_point``'s ``u`` gives, also a
    few ulps and a few margins from every edge and across the turn's wrap; near an edge, far
    from the walk's start or outside a sensor that does not wrap, it is unsure."""
    rng = np.random.default_rng(W)
    if wrap:
        sensor = SphericalSensor(
            width=W, height=8, max_range=80.0, el_min=-0.4, el_max=0.1, wrap=True
        )
    else:
        sensor = SphericalSensor(
            width=W, height=8, max_range=80.0, el_min=-0.4, el_max=0.1, az_min=-1.0, az_max=1.5
        )
    _, params, _ = sensor.kernel_args()
    edges = _k.column_edges(params)
    assert edges.shape == (2, W)
    az_min, daz = params[_k.P_AZ_MIN], params[_k.P_DAZ]
    a_edge = az_min + np.arange(W) * daz
    steps = (-3, -1.5, -0.5, 0.5, 1.5, 3)
    near = [a_edge + f * _k.COL_DIR_MARGIN for f in steps]
    near += [np.nextafter(a_edge, np.inf), np.nextafter(a_edge, -np.inf), a_edge]
    az = np.concatenate([rng.uniform(-np.pi, np.pi, 30000), *near, [np.pi, -np.pi, 0.0]])
    az = np.repeat(az, 3)
    rho = np.tile([0.3, 9.0, 70.0], len(az) // 3)
    xs, ys = rho * np.cos(az), rho * np.sin(az)
    xs[:3], ys[:3] = (2.0, -0.0, 0.0), (0.0, 0.0, -1.0)  # on the axes
    truth = np.empty((len(az), 2), np.int64)
    _columns_two_ways(params, edges, wrap, xs, ys, np.zeros(len(az), np.int64), truth)
    start = np.where(truth[:, 0] >= 0, truth[:, 0] + rng.integers(-4, 5, len(az)), 0)
    start = start % W if wrap else np.clip(start, 0, W - 2)  # within 4 columns of the answer
    out = np.empty((len(az), 2), np.int64)
    _columns_two_ways(params, edges, wrap, xs, ys, start, out)
    sure = out[:, 1] != _k.COLUMN_UNSURE
    assert np.array_equal(out[sure, 1], out[sure, 0])
    assert (out[sure, 1] >= 0).all()
    n_random = 3 * 30000
    inside = out[:n_random, 0] >= 0
    assert sure[:n_random][inside].mean() > 0.999  # random directions are not near an edge
    assert not sure[:n_random][~inside].any()  # outside the image: unsure, atan2 says it
    assert 0 < (~sure[n_random:]).sum() < 0.7 * (len(az) - n_random)  # the edges' own


@njit(cache=True)
def _band_two_ways(params, table, tans, chords, rng, fit, q_rho, shape, us, ts, rhos, ds, out):
    # per point (column u, tangent t, distance from the axis rho; a voxel at distance d):
    # out[m] = (row, fv - its chord, the chord's bound, the bilinear range, pass 3's
    # outcome (0 a value of the ramp, 1 logit(rho), 2 nothing), _band_outcome's)
    linear = shape == SHAPE_LINEAR
    for m in range(us.shape[0]):
        rho = rhos[m]
        z = ts[m] * rho
        t = z / rho
        r = _k.row_of_tangent(tans, t, 0)
        out[m, 0] = r
        if r < 0:
            continue
        u, v, _ = _k.spherical_in_column(params, table, us[m], rho, z)
        qu, qv = quad_origin(_k.SPHERICAL, params, u, v)
        chord = (tans[r] - t) * chords[0, r]
        out[m, 1] = (v - r) - chord
        out[m, 2] = chords[1, r]
        r_bil = bilinear(rng, qu, qv, u, v)
        out[m, 3] = r_bil
        value, inf = contribution(ds[m] - r_bil, r_bil, fit[0], fit[1], 0.01, fit[2], shape, q_rho)
        out[m, 4] = 2 if not inf else (1 if value == q_rho else 0)
        out[m, 5] = _band_outcome(rng, qu, r, u, chord, chords[1, r], ds[m], fit, linear)


@pytest.mark.parametrize("rows", ["table", "even"])
@pytest.mark.parametrize("fit", [(0.2, 0.0, 0.0), (0.05, 0.01, 0.3)])
def test_a_band_voxels_outcome_from_its_rows_chord_is_that_of_pass_3(rows: str, fit) -> None:
    """The kernel settles a LiDAR's band voxel as free or beyond the reach from the chord of
    its row in the tangent of the elevation, without its ``atan2``: the row's ``fv`` lies
    within the chord's bound (which the curvature of ``atan`` fills: the bound without it is
    broken), and where the outcome is sure it is pass 3's, also for voxels a hair from the
    thresholds; voxels within the margin go through pass 3."""
    rng = np.random.default_rng(11)
    e = make_dataset("street", length_m=8).scans[0][1].sensor.elevations
    W = 32  # a full turn: the last quad's right column is the first (its u up to W)
    if rows == "table":
        sensor = SphericalSensor(width=W, height=len(e), max_range=80.0, elevations=e, wrap=True)
    else:
        sensor = SphericalSensor(
            width=W, height=len(e), max_range=80.0, el_min=e[-1], el_max=e[0], wrap=True
        )
    _, params, table = sensor.kernel_args()
    tans = _k.row_tangents(params, table)
    chords = _k.row_chords(params, table, tans)
    ranges = rng.uniform(2.0, 80.0, (len(e), W))  # metres of jump between neighbours
    ranges[1::3] = ranges[::3][: len(ranges[1::3])]  # and quads whose two rows are the same
    n = 40000
    us = rng.uniform(0, W, n)
    ts = rng.uniform(tans[-1], tans[0], n)
    rhos = rng.uniform(0.5, 60.0, n)
    fit_a = np.array(fit, np.float64)
    q_rho = quantise(logit(0.01))
    out = np.zeros((n, 6))
    _band_two_ways(params, table, tans, chords, ranges, fit_a, q_rho, SHAPE_LINEAR, us, ts, rhos,
                   np.zeros(n), out)  # fmt: skip
    inside = out[:, 0] >= 0
    assert inside.mean() > 0.99
    dev, bound, r_bil = out[inside, 1], out[inside, 2], out[inside, 3]
    assert np.all(np.abs(dev) <= bound)
    assert np.abs(dev).max() > 0.3 * (bound - _k.ROW_CHORD_SLACK).max()  # the bound is needed
    # voxels spread over the band, and voxels a hair from each threshold
    eps = fit_a[0] + fit_a[1] * r_bil
    f = fit_a[2] if fit_a[2] > 0 else eps
    hairs = [0.0, 1e-16, 4e-16, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3, 1e-1]
    hair = rng.choice(hairs, len(r_bil)) * rng.choice([-1, 1], len(r_bil))
    ds = np.concatenate([
        r_bil + rng.uniform(-3.0, 3.0, len(r_bil)),
        r_bil + eps + f + hair * r_bil,  # beyond the reach or not
        r_bil - eps + hair * r_bil,  # free or on the ramp
    ])  # fmt: skip
    many = lambda a: np.tile(a[inside], 3)  # noqa: E731
    out = np.zeros((len(ds), 6))
    for shape in (SHAPE_LINEAR, 1):
        _band_two_ways(params, table, tans, chords, ranges, fit_a, q_rho, shape, many(us),
                       many(ts), many(rhos), ds, out)  # fmt: skip
        exact, sure = out[:, 4], out[:, 5]
        assert np.array_equal(exact[sure == BAND_FREE], np.full((sure == BAND_FREE).sum(), 1.0))
        assert np.all(exact[sure == BAND_NOTHING] == 2)
        # most of the spread voxels are beyond the reach or free (the ramp is 0.6 to 2 m)
        assert (sure[: len(r_bil)] != BAND_UNSURE).mean() > (0.6 if shape == SHAPE_LINEAR else 0.3)
        assert (sure == BAND_NOTHING).sum() > 1000
        assert ((sure == BAND_FREE).sum() > 1000) == (shape == SHAPE_LINEAR)
        near = np.abs(np.tile(hair, 2)) <= 1e-12
        assert np.all(sure[len(r_bil) :][near] == BAND_UNSURE)


def test_a_sensor_with_a_table_projects_and_unprojects_through_it() -> None:
    e = np.array([0.2, 0.15, 0.05, 0.0, -0.02, -0.3])
    s = SphericalSensor(width=8, height=6, max_range=50.0, elevations=tuple(e), wrap=True)
    v = np.array([0.0, 0.5, 2.25, 4.9, 5.0])
    p = s.unproject(np.zeros_like(v), v, np.full_like(v, 10.0))
    _, v_back, d = s.project(p)
    assert np.allclose(v_back, v, atol=1e-9) and np.allclose(d, 10.0)


def test_tiles_beyond_a_scans_sphere_are_out_of_its_view() -> None:
    """The planner hands a new scan only the tiles its sphere reaches: every other tile must
    be classified OUT (so the volume is the same bits as when every tile was tested)."""
    h = 0.2
    data = make_dataset("street", length_m=120)
    grid = GridSpec(h, 16, "mapping")
    params = FusionParams(NoiseModel(eps=2 * h))
    volume = Volume(grid, params)
    volume.add_many(data.scans[::6])
    keys = volume.tile_keys()
    for scan_id, _ in data.scans[::12]:
        if scan_id not in volume:
            continue
        scan = volume._prepare(scan_id)
        sphere = volume._sphere(scan_id)
        near = tiles_near(Sphere(scan_id, sphere.origin, sphere.radius_m), keys, grid)
        assert (~near).any()  # the street is longer than the sensor's reach
        for halo in (0, 1):
            status = classify_tiles(scan, grid, keys[~near], halo)
            assert (status == OUT).all()


def _tilted(pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``pose`` turned by a small random rotation (roll, pitch and yaw) about its origin."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.02, 0.3)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    out = pose.copy()
    out[:3, :3] = R @ pose[:3, :3]
    return out


@pytest.mark.parametrize(
    ("case", "h", "T"),
    [("level", 0.2, 16), ("tilted", 0.2, 16), ("no table", 0.2, 16), ("level", 0.1, 16),
     ("level", 0.1, 32), ("level", 0.02, 16)],
)  # fmt: skip
def test_the_parts_of_a_lidars_tiles_give_the_bits_of_the_voxel_loop(
    case: str, h: float, T: int
) -> None:
    """A spherical scan's kernel settles the parts and sub-parts of a partial tile that it
    sees out of view, behind the surface beyond its reach or free throughout, before any
    voxel, and a level column's run of a block at once (far from the sensor, at 2 cm): the
    same bits and the same informed counts as fusing every voxel of the tile (at 2 cm, on
    3,000 of the tiles)."""
    import dataclasses

    from rangefuse.engine.allocation import tiles_touched
    from rangefuse.engine.classify import FREE
    from rangefuse.engine.fusion import integrate_seen
    from rangefuse.engine.grid import unique_keys
    from rangefuse.engine.scans import prepare_scan

    rng = np.random.default_rng(len(case))
    data = make_dataset("street", length_m=120)
    grid = GridSpec(h, T, "mapping")
    params = FusionParams(NoiseModel(eps=2 * h))
    scans = [scan for _, scan in data.scans[10:50:13]]
    if case == "tilted":
        scans = [dataclasses.replace(s, T_W_S=_tilted(s.T_W_S, rng)) for s in scans]
    if case == "no table":  # rows evenly spaced over the same span, the ranges unchanged
        e = scans[0].sensor.elevations
        sensor = dataclasses.replace(scans[0].sensor, elevations=None, el_max=e[0], el_min=e[-1])
        scans = [dataclasses.replace(s, sensor=sensor) for s in scans]
    prepared = [prepare_scan(s, params) for s in scans]
    keys = unique_keys(np.concatenate([tiles_touched(p, grid) for p in prepared]))
    if len(keys) > 3000:
        keys = keys[np.sort(rng.choice(len(keys), 3000, replace=False))]
    for scan in prepared:
        status = classify_tiles(scan, grid, keys)
        rows = np.flatnonzero(status != OUT)
        free = status[rows] == FREE
        fused = []
        for parts in (True, False):
            data_ = np.zeros((len(keys), T, T, T), np.int64)
            informed = integrate_seen(scan, grid, keys, data_, rows, free, 1, parts=parts)
            fused.append((data_, informed))
        assert np.array_equal(fused[0][0], fused[1][0])
        assert np.array_equal(fused[0][1], fused[1][1])
        assert (fused[0][1] > 0).sum() > 100


@pytest.mark.slow
def test_lidar_benchmark_smoke(tmp_path) -> None:
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "lidar.py"
    octomap = "2" if importlib.util.find_spec("pyoctomap") is not None else "0"
    out = subprocess.run(
        [sys.executable, str(script), "--voxels", "0.2", "--lengths", "8", "--octomap-scans",
         octomap, "--group-scans", "2", "--tmp", str(tmp_path)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [line.split() for line in out.stdout.splitlines() if line.startswith("  0.20")]
    assert [r[2:4] for r in rows[:2]] == [["rangefuse", "memory"], ["rangefuse", "store"]]
    assert all(int(r[4]) == 4 for r in rows[:2])  # one scan per 2 m
    assert rows[0][9] == rows[1][9]  # the same tiles in memory and in the store
    assert rows[0][-5] == rows[1][-5] and float(rows[0][-5]) > 0  # and the same voxel updates
    # the kernel's share, the tiles written per scan and the tile array's files: a store's
    assert rows[0][-3:] == ["-", "-", "-"]
    assert 0 < float(rows[1][-3].rstrip("%")) <= 100 and int(rows[1][-2]) > 0
    assert 0 < int(rows[1][-1]) < int(rows[1][9])  # tiles in shards: fewer files than tiles
    if octomap != "0":
        assert "faster than OctoMap" in out.stdout
    # --tilt: the street rendered again from rolled and pitched poses
    tilted = subprocess.run(
        [sys.executable, str(script), "--voxels", "0.2", "--lengths", "8", "--octomap-scans",
         "0", "--no-store", "--tilt", "0.05"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert tilted.returncode == 0, tilted.stderr[-3000:]
    assert "poses tilted by up to 0.05 rad" in tilted.stdout
    (row,) = [line.split() for line in tilted.stdout.splitlines() if line.startswith("  0.20")]
    assert int(row[4]) == 4 and row[9] != rows[0][9]  # other poses reach other tiles
    bad = subprocess.run(
        [sys.executable, str(script), "--tilt", "2"], capture_output=True, text=True, timeout=60
    )
    assert bad.returncode != 0 and "--tilt: give 0 to 0.5 radians, got 2.0" in bad.stderr


def _catalog(tmp_path):
    from rangefuse.storage.catalog import Catalog

    catalog = Catalog(tmp_path / "catalog.sqlite")
    catalog.create_scene("s", "s", "t", {}, {})
    return catalog


@pytest.mark.parametrize("seed", range(4))
def test_the_catalogs_search_finds_every_scan_near_a_box(tmp_path, seed: int) -> None:
    """The catalog's indexed search returns a superset of the fused scans whose sphere meets a
    box (the planner's test then picks the same ones as from every scan), in sequence order."""
    from rangefuse.engine.planner import scans_near

    rng = np.random.default_rng(seed)
    catalog = _catalog(tmp_path)
    grid = GridSpec(0.1, 16, "mapping")
    tile_m = grid.tile_size_m
    with catalog.transaction():
        for n in range(300):
            origin = rng.uniform(-400, 400, 3) * (1, 0.1, 0.01)
            reach = float(rng.choice([2.0, 30.0, 80.0, math.inf], p=[0.3, 0.3, 0.39, 0.01]))
            catalog.add_scan("s", f"a{n}", None, origin.tolist(), reach, "x")
    fused = [f"a{n}" for n in range(300) if rng.random() < 0.7]
    catalog.set_scan_state("s", fused, "fused")
    rows = catalog.scans("s", ("fused",))
    every = [Sphere(r.id, r.origin, r.reach_m) for r in rows]
    for _ in range(30):
        lo = rng.integers(-300, 300, 3) * (1, 0, 0) + rng.integers(-5, 5, 3)
        keys = lo + rng.integers(0, 40, (5, 3))
        box_lo = keys.min(axis=0) * tile_m
        box_hi = (keys.max(axis=0) + 1) * tile_m
        found = catalog.scans_near_box("s", box_lo.tolist(), box_hi.tolist(), tile_m)
        assert [r.seq for r in found] == sorted(r.seq for r in found)
        assert {r.state for r in found} <= {"fused"}
        candidates = [Sphere(r.id, r.origin, r.reach_m) for r in found]
        assert scans_near(candidates, keys, grid) == scans_near(every, keys, grid)


def test_the_catalog_lists_the_tiles_in_key_ranges(tmp_path) -> None:
    from rangefuse.engine.grid import pack_keys, unique_keys

    rng = np.random.default_rng(7)
    catalog = _catalog(tmp_path)
    keys = unique_keys(rng.integers(-50, 50, (2000, 3)))
    packed = pack_keys(keys)
    owner = rng.random(len(keys)) < 0.8
    with catalog.transaction():
        catalog.add_tile_scans("s", [("a", packed, owner)])
        catalog.add_tile_scans("s", [("b", packed[::3], np.zeros(len(packed[::3]), np.bool_))])
    owned = packed[owner]
    ranges = [(int(a), int(b)) for a, b in sorted(rng.choice(owned, (6, 2)).tolist())]
    ranges = [(a, b) for (a, b), nxt in zip(ranges, [*ranges[1:], (None, None)], strict=True)
              if nxt[0] is None or b < nxt[0]]  # fmt: skip
    expected = np.concatenate([owned[(owned >= a) & (owned <= b)] for a, b in ranges])
    assert np.array_equal(catalog.tile_keys_in_ranges("s", ranges), expected)


def test_the_catalogs_log_shrinks_back_after_a_large_group(tmp_path, monkeypatch) -> None:
    """A group's checkpoint is one transaction that writes a row per tile; once SQLite has
    checkpointed its log, the next transaction cuts the log back to WAL_LIMIT."""
    from rangefuse.storage import catalog as catalog_module

    monkeypatch.setattr(catalog_module, "WAL_LIMIT", 64 * 1024)
    catalog = _catalog(tmp_path)
    wal = tmp_path / "catalog.sqlite-wal"
    keys = np.arange(100_000, dtype=np.int64)
    with catalog.transaction():
        catalog.add_tile_scans(
            "s", [(scan, keys, np.zeros(len(keys), np.bool_)) for scan in "abcdefg"]
        )
    # the group's log, past SQLite's automatic checkpoint (1,000 pages)
    assert wal.stat().st_size > 4096 * 1000
    with catalog.transaction():
        catalog.add_tile_scans("s", [("d", keys[:1], np.ones(1, np.bool_))])
    assert wal.stat().st_size <= 64 * 1024


def _pairs(catalog, scene_id: str) -> set[tuple[int, str, bool]]:
    """Every (tile, scan, owner) entry of the scene's rows, whether or not the tile exists."""
    from rangefuse.storage._tile_rows import entries

    num = catalog._num(scene_id)
    ids = dict(catalog._db.execute("SELECT num, id FROM scan_nums WHERE scene=?", (num,)))
    rows = catalog._db.execute("SELECT tile, owners, scans FROM tile_scans WHERE scene=?", (num,))
    out = set()
    for tile, owners, blob in rows:
        e = entries(blob)
        assert np.all(np.diff(e >> 1) > 0) and owners == int((e & 1).sum())
        out |= {
            (tile, ids[n], bool(o))
            for n, o in zip((e >> 1).tolist(), (e & 1).tolist(), strict=True)
        }
    return out


def test_the_catalogs_rows_per_tile_merge_as_rows_per_pair_did(tmp_path, monkeypatch) -> None:
    """A checkpoint's pairs merge into a row per tile (catalog version 3) as a row per pair
    did: a scan's later entry in a tile replaces its earlier one, whatever the batches
    (``MERGE_PAIRS``, ``MERGE_TILES``); owners set by a TileStore keep the other scans as
    informing ones; a removal in the ranges that hold its tiles takes every entry of its
    scan."""
    rng = np.random.default_rng(3)
    model: dict[tuple[int, str], bool] = {}
    scans = []
    for n in range(12):
        tiles = np.unique(rng.integers(0, 400, rng.integers(1, 150)))
        owner = rng.random(len(tiles)) < 0.6
        scans.append((f"s{n % 9}", tiles, owner))  # three scans come twice
        model.update(
            {(t, f"s{n % 9}"): bool(o) for t, o in zip(tiles.tolist(), owner.tolist(), strict=True)}
        )
    found = []
    for batch, tiles_at_once in ((2**21, 2**16), (100, 7)):
        monkeypatch.setattr("rangefuse.storage._tile_rows.MERGE_PAIRS", batch)
        monkeypatch.setattr("rangefuse.storage._tile_rows.MERGE_TILES", tiles_at_once)
        (tmp_path / str(batch)).mkdir()
        catalog = _catalog(tmp_path / str(batch))
        with catalog.transaction():
            catalog.add_tile_scans("s", scans[:5])
            catalog.add_tile_scans("s", scans[5:])
        found.append(_pairs(catalog, "s"))
        owned = sorted({t for (t, _), o in model.items() if o})
        assert np.array_equal(catalog.tile_keys("s"), owned)
        assert catalog.n_tiles("s") == len(owned)
    assert found[0] == found[1] == {(t, s, o) for (t, s), o in model.items()}

    tiles = np.array(sorted({t for t, _ in model})[:20], np.int64)
    with catalog.transaction():
        catalog.set_tile_owners("s", tiles, [frozenset({"s1", "x"})] * len(tiles))
    for t in tiles.tolist():
        for s in [s for (tt, s) in model if tt == t]:
            model[(t, s)] = False
        model[(t, "s1")] = model[(t, "x")] = True
    assert _pairs(catalog, "s") == {(t, s, o) for (t, s), o in model.items()}
    info = catalog.tile_scans("s", tiles)
    assert {(t, s, o) for t, v in info.items() for s, o in v} == {
        (t, s, o) for (t, s), o in model.items() if t in set(tiles.tolist())
    }

    with catalog.transaction():
        catalog.remove_tile_scans("s", "s2", [(0, 99), (100, 500)])
        catalog.remove_tile_scans("s", "x")
    model = {(t, s): o for (t, s), o in model.items() if s not in ("s2", "x")}
    assert _pairs(catalog, "s") == {(t, s, o) for (t, s), o in model.items()}
    assert "s2" not in {r[0] for r in catalog._db.execute("SELECT id FROM scan_nums")}
