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
    if octomap != "0":
        assert "faster than OctoMap" in out.stdout
