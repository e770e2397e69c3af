"""The planner's spatial indexes answer exactly what a pass over everything answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rangefuse.engine.grid import GridSpec, unique_keys
from rangefuse.engine.planner import Sphere, scans_near, tiles_near
from rangefuse.engine.spatial import SphereIndex, TileIndex, shift_for

GRID = GridSpec(0.1, 16, "mapping")
TILE_M = GRID.tile_size_m


def _random_keys(rng: np.random.Generator, n: int, spread: int) -> np.ndarray:
    """Sorted unique keys: a street-like strip along x with clusters, negatives included."""
    x = rng.integers(-spread, spread, n)
    y = rng.integers(-spread // 8 - 1, spread // 8 + 1, n)
    z = rng.integers(-3, 4, n)
    return unique_keys(np.stack([x, y, z], axis=1))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("shift", [0, 1, 3, 5])
def test_rows_in_box_are_those_of_the_brute_force_pass(seed: int, shift: int) -> None:
    rng = np.random.default_rng(seed)
    keys = _random_keys(rng, int(rng.integers(1, 3000)), int(rng.integers(4, 400)))
    index = TileIndex(keys, shift)
    for _ in range(25):
        a = rng.integers(-450, 450, 3)
        b = a + rng.integers(-3, 300, 3)  # empty boxes too (hi < lo on an axis)
        expected = np.flatnonzero(np.all((keys >= a) & (keys <= b), axis=1))
        assert np.array_equal(index.rows_in_box(a, b), expected)


@pytest.mark.parametrize("seed", range(8))
def test_rows_near_are_the_tiles_near_a_sphere(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    keys = _random_keys(rng, int(rng.integers(1, 4000)), int(rng.integers(8, 600)))
    for radius in (0.0, 0.7, 12.0, 80.0, 500.0, math.inf):
        index = TileIndex(keys, shift_for(radius, TILE_M))
        for _ in range(10):
            origin = tuple(float(x) for x in rng.uniform(-700.0, 700.0, 3) * (1, 0.2, 0.01))
            sphere = Sphere("s", origin, radius)  # type: ignore[arg-type]
            expected = np.flatnonzero(tiles_near(sphere, keys, GRID))
            assert np.array_equal(index.rows_near(origin, radius, TILE_M), expected)


def test_an_empty_index_finds_nothing() -> None:
    index = TileIndex(np.zeros((0, 3), np.int64), 3)
    assert len(index.rows_in_box(np.array([-5, -5, -5]), np.array([5, 5, 5]))) == 0
    assert len(index.rows_near((0.0, 0.0, 0.0), 50.0, TILE_M)) == 0


@pytest.mark.parametrize("seed", range(8))
def test_sphere_index_finds_the_scans_near_tiles_in_order(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    index = SphereIndex(cell_m=float(rng.choice([4.0, 16.0, 64.0])))
    spheres: dict[str, Sphere] = {}
    for n in range(int(rng.integers(0, 400))):
        radius = float(rng.choice([0.0, 3.0, 40.0, 80.0, math.inf], p=[0.1, 0.3, 0.3, 0.28, 0.02]))
        origin = tuple(float(x) for x in rng.uniform(-500.0, 500.0, 3) * (1, 0.1, 0.01))
        spheres[f"s{n}"] = Sphere(f"s{n}", origin, radius)  # type: ignore[arg-type]
        index.add(f"s{n}", origin, radius)
    for scan_id in list(spheres)[::3]:  # removals, and re-adding one moves it to the end
        del spheres[scan_id]
        index.remove(scan_id)
    if spheres:
        again = next(iter(spheres))
        spheres[again] = spheres.pop(again)
        index.add(again, spheres[again].origin, spheres[again].radius_m)
    assert len(index) == len(spheres)
    for _ in range(20):
        keys = _random_keys(rng, int(rng.integers(1, 30)), int(rng.integers(1, 200)))
        keys = keys + rng.integers(-300, 300, 3) * (1, 0, 0)
        lo = keys.min(axis=0) * TILE_M
        hi = (keys.max(axis=0) + 1) * TILE_M
        assert index.near_box(lo, hi, TILE_M) == scans_near(spheres.values(), keys, GRID)


def test_sphere_index_refuses_a_bad_cell() -> None:
    with pytest.raises(ValueError, match="cell_m"):
        SphereIndex(cell_m=0.0)
