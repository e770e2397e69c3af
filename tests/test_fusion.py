"""Fusion: agreement with the dense reference, order independence, exact removal."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rangefuse.engine import (
    FusionParams,
    GridSpec,
    InvalidGridError,
    InvalidInputError,
    InvalidScanError,
    NoiseModel,
    Scan,
    ScanNotFoundError,
    Volume,
    allocation,
    decode_count,
    decode_logodds,
    prepare_scan,
)
from rangefuse.engine._sampling import QUAD_BLOCK
from rangefuse.engine.allocation import tiles_touched
from rangefuse.engine.classify import FREE, OUT, classify_tiles
from rangefuse.engine.defaults import COUNT_BITS, LOGIT_SCALE
from rangefuse.engine.fusion import integrate_seen
from rangefuse.engine.grid import KEY_LIMIT, unique_keys
from rangefuse.engine.synth import make_dataset

from tests import reference, scenes

H = 0.02  # voxel size of the small scene


def _params(**kwargs) -> FusionParams:
    noise = kwargs.pop("noise", NoiseModel(eps=0.03, rho=0.08))
    return FusionParams(noise=noise, **kwargs)


def _dense_packed(volume: Volume, lo: np.ndarray, shape: tuple[int, ...]):
    """Packed voxels over [lo, lo + shape) and a mask of voxels inside allocated tiles."""
    T = volume.grid.tile_size
    packed = np.zeros(shape, np.int64)
    allocated = np.zeros(shape, bool)
    keys = volume.tile_keys()
    for key, tile in zip(keys, volume.store.read(keys), strict=True):
        a0 = key * T
        s_lo = np.maximum(lo - a0, 0)
        s_hi = np.minimum(lo + shape - a0, T)
        if np.any(s_hi <= s_lo):
            continue
        d_lo = a0 + s_lo - lo
        d_hi = a0 + s_hi - lo
        dst = tuple(slice(d_lo[i], d_hi[i]) for i in range(3))
        packed[dst] = tile[tuple(slice(s_lo[i], s_hi[i]) for i in range(3))]
        allocated[dst] = True
    return packed, allocated


def _compare_with_reference(volume: Volume, scans: list[tuple[str, Scan]], bounds=scenes.BOUNDS):
    grid = GridSpec(volume.grid.voxel_size, volume.grid.tile_size, "mapping", bounds)
    lo, hi = grid.roi_voxels()
    shape = tuple(int(x) for x in hi - lo)
    ref = reference.fuse([s for _, s in scans], volume.params, lo, shape, volume.grid.voxel_size)
    packed, allocated = _dense_packed(volume, lo, shape)
    count = decode_count(packed)
    L = decode_logodds(packed)
    # inside allocated tiles: the same informed voxels, the same log-odds within quantisation
    assert np.array_equal(count[allocated], ref.count[allocated])
    inf = allocated & (count > 0)
    tol = count[inf] * 0.5 / LOGIT_SCALE + 1e-6 * np.abs(ref.logodds[inf]) + 1e-6
    err = np.abs(L[inf] - ref.logodds[inf])
    assert np.all(err <= tol), f"max error {err.max()} at tolerance {tol[np.argmax(err - tol)]}"
    # outside allocated tiles: nothing of the surface band is missing
    assert not np.any(ref.band & ~allocated), "band voxels outside allocated tiles"
    if volume.grid.mode == "closed":
        # closed mode allocates every tile in view: no informed voxel is left out
        assert not np.any((ref.count > 0) & ~allocated)
    return ref, count


@pytest.mark.parametrize("name", sorted(scenes.SENSORS))
@pytest.mark.parametrize("mode", ["mapping", "closed"])
def test_matches_dense_reference(name: str, mode: str) -> None:
    scans = scenes.scans(name, 4)
    volume = Volume(GridSpec(H, 8, mode, scenes.BOUNDS), _params())
    volume.add_many(scans)
    assert len(volume.tile_keys()) > 0
    ref, _ = _compare_with_reference(volume, scans)
    assert (ref.count > 0).sum() > 1000, "the scene should inform a good part of the grid"


def test_mapping_allocation_is_tight() -> None:
    # Most tiles a scan allocates hold a voxel of its surface band (the contribution is
    # neither free space nor nothing). Allocation boxes each pixel quad's band; the 4 x 4
    # quad blocks it used to box at once gave 0.49 on this case, quad by quad gives 0.77.
    h, T = 0.01, 16
    data = make_dataset("room", views=6)
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    grid = GridSpec(h, T, "mapping")
    allocated = needed = 0
    for _, scan in data.scans:
        prepared = prepare_scan(scan, params)
        keys = tiles_touched(prepared, grid)
        packed = np.zeros((len(keys), T, T, T), np.int64)
        status = classify_tiles(prepared, grid, keys)
        rows = np.flatnonzero(status != OUT)
        integrate_seen(prepared, grid, keys, packed, rows, status[rows] == FREE, 1)
        band = (decode_count(packed) > 0) & (packed >> COUNT_BITS != prepared.q_rho)
        allocated += len(keys)
        needed += int(band.reshape(len(keys), -1).any(axis=1).sum())
    assert needed / allocated > 0.7


@pytest.mark.parametrize("name", ["room", "street"])
def test_allocation_walk_overflow_gives_the_same_tiles(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The walk holds _WALK_ROOM keys per top node and walks a node again when it emits
    # more; with room for one key nearly every node walks twice, with the same tiles.
    h = 0.02
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    grid = GridSpec(h, 16, "mapping")
    for _, scan in make_dataset(name, views=2).scans:
        prepared = prepare_scan(scan, params)
        expected = tiles_touched(prepared, grid)
        monkeypatch.setattr(allocation, "_WALK_ROOM", 1)
        assert np.array_equal(tiles_touched(prepared, grid), expected)
        monkeypatch.undo()
    assert len(expected) > 100


def test_tile_classification_is_conservative_around_a_pinhole() -> None:
    # Every tile within 1 m of the camera, many of them across the plane z = 0 through it
    # (their pixel rectangle is unbounded). OUT: the kernel, voxel by voxel, informs none
    # of its voxels; FREE: it informs all of them, with logit(rho). Tiles across that
    # plane but beside the image's pyramid are OUT (they used to be fused for nothing).
    h, T = 0.02, 8
    data = make_dataset("room", views=3)
    params = FusionParams(NoiseModel(eps=2 * h, rho=0.05))
    grid = GridSpec(h, T, "mapping")
    span = np.arange(-6, 7)
    offsets = np.stack(np.meshgrid(span, span, span, indexing="ij"), -1).reshape(-1, 3)
    corners = np.stack(
        np.meshgrid([0.5, T - 0.5], [0.5, T - 0.5], [0.5, T - 0.5], indexing="ij"), -1
    ).reshape(-1, 3)
    crossing_out = crossing_empty = 0
    for _, scan in data.scans:
        prepared = prepare_scan(scan, params)
        keys = np.floor(prepared.origin_W / (T * h)).astype(np.int64) + offsets
        status = classify_tiles(prepared, grid, keys)
        packed = np.zeros((len(keys), T, T, T), np.int64)
        rows = np.arange(len(keys))
        informed = integrate_seen(prepared, grid, keys, packed, rows, np.zeros(len(keys), bool), 1)
        assert not np.any(informed[status == OUT])
        free = status == FREE
        assert np.all(informed[free] == T**3)
        assert np.all(packed[free] >> COUNT_BITS == prepared.q_rho)
        # tiles across the sensor's plane z = 0
        world = (keys[:, None, :] * T + corners[None]) * h
        z = world @ prepared.M[2] + prepared.c[2]
        crossing = (z.min(axis=1) <= 0.0) & (z.max(axis=1) > 0.0)
        crossing_out += int(np.sum(crossing & (status == OUT)))
        crossing_empty += int(np.sum(crossing & (informed == 0)))
    assert crossing_empty > 100
    assert crossing_out > 0.8 * crossing_empty


@pytest.mark.parametrize(
    "options",
    [
        {"noise": NoiseModel(eps=0.02, rho=0.1, shape="erf")},
        {"noise": NoiseModel(eps=0.01, eps_per_m=0.02, rho=0.05, falloff=0.05)},
        {"filter": "mean5"},
        {"filter": "median3"},
        {"max_discontinuity": 0.05},
        {"no_return": "invalid"},
    ],
    ids=["erf", "eps_per_m+falloff", "mean5", "median3", "discontinuity", "no_return_invalid"],
)
def test_options_match_dense_reference(options: dict) -> None:
    scans = scenes.scans("pinhole_ray", 3) + scenes.scans("spherical", 2)
    volume = Volume(GridSpec(H, 8, "closed", scenes.BOUNDS), _params(**options))
    volume.add_many(scans)
    _compare_with_reference(volume, scans)


def test_per_scan_noise_override_matches_reference() -> None:
    scans = scenes.scans("pinhole_z", 3)
    name, first = scans[0]
    scans[0] = (
        name,
        Scan(first.range_m, first.T_W_S, first.sensor, noise=NoiseModel(eps=0.06, rho=0.2)),
    )
    volume = Volume(GridSpec(H, 8, "closed", scenes.BOUNDS), _params())
    volume.add_many(scans)
    _compare_with_reference(volume, scans)


def _state(volume: Volume):
    keys = volume.tile_keys()
    return keys, volume.store.read(keys), volume.store.owners(keys)


def _assert_same(a: Volume, b: Volume) -> None:
    ka, da, oa = _state(a)
    kb, db, ob = _state(b)
    assert np.array_equal(ka, kb)
    assert np.array_equal(da, db)
    assert oa == ob


MIXED = scenes.scans("pinhole_ray", 3) + scenes.scans("spherical", 2) + scenes.scans("linescan", 1)


@settings(max_examples=12, deadline=None)
@given(order=st.permutations(range(len(MIXED))), mode=st.sampled_from(["mapping", "closed"]))
def test_order_does_not_change_the_volume(order: list[int], mode: str) -> None:
    grid = GridSpec(H, 8, mode, scenes.BOUNDS)
    batch = Volume(grid, _params())
    batch.add_many(MIXED)
    one_by_one = Volume(grid, _params())
    for k in order:
        one_by_one.add(*MIXED[k])
    _assert_same(batch, one_by_one)


def test_late_tiles_receive_earlier_scans_and_new_scans_carve_old_tiles() -> None:
    # Two cameras on opposite sides: B's surface tiles lie in free space that A saw through
    # and A's surface tiles lie in B's free space (mapping mode, no bounds).
    scans = scenes.scans("pinhole_ray", 2)
    grid = GridSpec(H, 8, "mapping")
    a = Volume(grid, _params())
    a.add(*scans[0])
    keys_a = a.tile_keys()
    report = a.add(*scans[1])
    assert len(report.created) > 0
    # a tile that only B created received A's contribution too ...
    both = Volume(grid, _params())
    both.add_many(scans)
    _assert_same(a, both)
    only_b = Volume(grid, _params())
    only_b.add(*scans[1])
    kb, db, _ = _state(only_b)
    rows = [i for i, k in enumerate(kb) if not any((k == keys_a).all(1))]
    keys_all, data_all, _ = _state(both)
    idx = {tuple(k): i for i, k in enumerate(keys_all)}
    differs = [not np.array_equal(db[i], data_all[idx[tuple(kb[i])]]) for i in rows]
    assert any(differs), "no late tile received the earlier scan"
    # ... and B changed tiles that only A touched (it sees through them)
    changed = {tuple(k) for k in report.changed}
    assert any(tuple(k) in changed for k in keys_a)


@pytest.mark.parametrize("mode", ["mapping", "closed"])
def test_removal_restores_the_volume_exactly(mode: str) -> None:
    grid = GridSpec(H, 8, mode, scenes.BOUNDS)
    deleted = 0
    for k, (scan_id, scan) in enumerate(MIXED):
        volume = Volume(grid, _params())
        volume.add_many(MIXED)
        report = volume.remove(scan_id)
        without = Volume(grid, _params())
        without.add_many([item for j, item in enumerate(MIXED) if j != k])
        _assert_same(volume, without)
        assert scan_id not in volume
        deleted += len(report.deleted)
        volume.add(scan_id, scan)  # re-adding restores the full volume
        full = Volume(grid, _params())
        full.add_many(MIXED)
        _assert_same(volume, full)
    assert deleted > 0 or mode == "closed", "some scan should own tiles alone"


def test_removing_every_scan_leaves_nothing() -> None:
    volume = Volume(GridSpec(H, 8, "mapping"), _params())
    volume.add_many(MIXED)
    for scan_id, _ in MIXED:
        volume.remove(scan_id)
    assert len(volume.tile_keys()) == 0


def test_thread_count_does_not_change_the_volume() -> None:
    grid = GridSpec(H, 8, "closed", scenes.BOUNDS)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = Volume(grid, _params())
        one.add_many(MIXED)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = Volume(grid, _params())
        many.add_many(MIXED)
    finally:
        numba.set_num_threads(previous)
    _assert_same(one, many)


def test_unknown_stays_distinct_and_free_space_is_negative() -> None:
    scans = scenes.scans("pinhole_ray", 4)
    volume = Volume(GridSpec(H, 8, "closed", scenes.BOUNDS), _params())
    volume.add_many(scans)
    dense = volume.to_dense()
    L = dense.logodds
    assert np.isnan(L).any() and (L < 0).any() and (L > 0).any()
    # the centre of the box is never seen: unknown, not zero
    centre = np.round((np.array([0.05, -0.05, -0.1]) - dense.origin) / H).astype(int)
    assert np.isnan(L[tuple(centre)])
    # a corner of the region of interest far from everything is free
    assert L[0, 0, -1] < 0


def test_grid_spec_errors() -> None:
    with pytest.raises(InvalidGridError, match="^voxel_size:"):
        GridSpec(0.0)
    with pytest.raises(InvalidGridError, match="^voxel_size:"):
        GridSpec(float("nan"))
    with pytest.raises(InvalidGridError, match="^tile_size:"):
        GridSpec(0.01, 2)
    with pytest.raises(InvalidGridError, match="^mode:"):
        GridSpec(0.01, 16, "open")
    with pytest.raises(InvalidGridError, match="^bounds: closed mode needs"):
        GridSpec(0.01, 16, "closed")
    with pytest.raises(InvalidGridError, match="^bounds: x0 must be less than x1"):
        GridSpec(0.01, 16, "closed", (1, 0, 0, 0, 1, 1))
    with pytest.raises(InvalidGridError, match="^bounds: must be six"):
        GridSpec(0.01, 16, "closed", (0, 0, 0, 1, 1))
    with pytest.raises(InvalidGridError, match="^bounds: the box holds no voxel centre"):
        GridSpec(1.0, 16, "closed", (0.1, 0.1, 0.1, 0.2, 0.2, 0.2))


def test_scan_errors() -> None:
    _, good = scenes.scans("pinhole_ray", 1)[0]
    s, rng, T = good.sensor, good.range_m, good.T_W_S
    cases = [
        (dict(range_m=np.zeros(rng.shape, np.int16)), "range", "floating-point"),
        (dict(range_m=rng[:, :-1]), "range", "does not match the sensor"),
        (dict(range_m=rng[None]), "range", "2-D"),
        (dict(range_m=np.where(np.isfinite(rng), -rng, rng)), "range", "<= 0"),
        (dict(range_m=list(rng)), "range", "NumPy array"),
        (dict(T_W_S=np.full((4, 4), np.nan)), "pose", "non-finite"),
        (dict(T_W_S=np.eye(3)), "pose", "4x4"),
        (dict(T_W_S=np.diag([2.0, 1.0, 1.0, 1.0])), "pose", "not rigid"),
        (dict(T_W_S=np.diag([-1.0, 1.0, 1.0, 1.0])), "pose", "reflection"),
        (dict(T_W_S=np.vstack([T[:3], [0, 0, 1, 1]])), "pose", "last row"),
        (dict(sensor="pinhole"), "sensor", "must be a Sensor"),
    ]
    for change, field, words in cases:
        kwargs = dict(range_m=rng, T_W_S=T, sensor=s) | change
        with pytest.raises(InvalidScanError) as info:
            Scan(**kwargs)
        assert str(info.value).startswith(field + ":"), str(info.value)
        assert words in str(info.value), str(info.value)


def test_volume_errors() -> None:
    scans = scenes.scans("pinhole_ray", 1)
    volume = Volume(GridSpec(H, 8), _params())
    volume.add_many(scans)
    with pytest.raises(InvalidInputError, match="already in the volume"):
        volume.add(*scans[0])
    with pytest.raises(InvalidInputError, match="^scan_id:"):
        volume.add("", scans[0][1])
    with pytest.raises(InvalidInputError, match="^scan:"):
        volume.add("x", "not a scan")  # type: ignore[arg-type]
    with pytest.raises(ScanNotFoundError):
        volume.remove("nope")
    with pytest.raises(InvalidInputError, match="^filter:"):
        _params(filter="blur")
    with pytest.raises(InvalidInputError, match="^no_return:"):
        _params(no_return="maybe")
    with pytest.raises(InvalidInputError, match="^max_discontinuity:"):
        _params(max_discontinuity=-1.0)
    # a failed add leaves the volume as it was
    keys_before = volume.tile_keys()
    assert np.array_equal(keys_before, volume.tile_keys())
    assert volume.scan_ids == [scans[0][0]]


@pytest.mark.parametrize("name", list(scenes.SENSORS))
@pytest.mark.parametrize("filter_name", ["none", "median3", "mean5"])
def test_bounding_sphere_holds_everything_the_scan_informs(name, filter_name):
    """The kernel-free sphere the service records is never tighter than the scan's reach."""
    from rangefuse.engine.classify import bounding_sphere, reach_radius

    for no_return in ("free", "invalid"):
        params = _params(filter=filter_name, no_return=no_return)
        for _, scan in scenes.scans(name, 2):
            origin, radius = bounding_sphere(scan, params)
            prepared = prepare_scan(scan, params)
            np.testing.assert_array_equal(origin, prepared.origin_W)
            assert radius >= reach_radius(prepared) or not np.isfinite(prepared.reach_max)


_CACHE_PROBE = """
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
from rangefuse.engine.synth import make_dataset
params = FusionParams(NoiseModel(eps=0.05, rho=0.05))
for name, h in (("room", 0.04), ("street", 0.08)):
    data = make_dataset(name, views=1, length_m=4.0 if name == "street" else None)
    volume = Volume(GridSpec(h, 8, "mapping"), params)
    volume.add_many(data.scans)
    volume.extract_mesh()
"""


def test_kernels_compiled_once_load_from_the_cache_in_a_new_process(tmp_path):
    """A second process running the same fusion and meshing compiles nothing: numba keys its
    cache on a kernel's closure variables, so a factory whose kernels capture compiled
    functions (instead of plain constants) misses the cache in every process."""
    cache = os.environ.get("NUMBA_CACHE_DIR") or str(tmp_path / "numba")
    env = {**os.environ, "NUMBA_CACHE_DIR": cache}

    def run_and_list() -> set[str]:
        done = subprocess.run(
            [sys.executable, "-c", _CACHE_PROBE], env=env, capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr
        return {str(p.relative_to(cache)) for p in Path(cache).rglob("*") if p.is_file()}

    first = run_and_list()
    second = run_and_list()
    assert sorted(second - first) == []


def test_a_prepared_scan_shares_the_range_map_unless_it_must_change_it() -> None:
    # prepared scans stay cached while their volume lives: no copy when nothing changes
    _, first = scenes.scans("pinhole_z", 1)[0]
    scan = Scan(
        np.where(np.isposinf(first.range_m), np.nan, first.range_m), first.T_W_S, first.sensor
    )
    prepared = prepare_scan(scan, _params())
    assert prepared.range_m is scan.range_m and prepared.surface_m is scan.range_m
    # no-return pixels: free space up to max_range for the range, NaN on the surface
    rng = scan.range_m.copy()
    rng[:5] = np.inf
    late = Scan(rng, scan.T_W_S, scan.sensor)
    prepared = prepare_scan(late, _params())
    assert np.all(prepared.range_m[:5] == np.float32(scan.sensor.max_range))
    assert np.all(np.isnan(prepared.surface_m[:5]))
    assert np.array_equal(prepared.surface_m[5:], late.range_m[5:], equal_nan=True)
    assert np.isposinf(late.range_m[:5]).all()  # the scan itself is untouched
    for array in (prepared.range_m, prepared.surface_m, late.range_m):
        assert not array.flags.writeable


def test_unique_keys_sorts_and_deduplicates_and_refuses_keys_beyond_the_limit() -> None:
    rng = np.random.default_rng(3)
    keys = np.concatenate(
        [
            rng.integers(-5, 5, (500, 3)),
            [[KEY_LIMIT - 1, -(KEY_LIMIT - 1), 0], [-(KEY_LIMIT - 1), KEY_LIMIT - 1, 7]],
        ]
    ).astype(np.int64)
    expected = np.unique(keys, axis=0)  # lexicographic rows
    assert np.array_equal(unique_keys(keys), expected)
    assert np.array_equal(unique_keys(keys[::-1]), expected)
    assert unique_keys(np.zeros((0, 3), np.int64)).shape == (0, 3)
    for bad in ([0, 0, KEY_LIMIT], [-KEY_LIMIT, 0, 0]):
        with pytest.raises(InvalidGridError, match="^bounds: the scene extends beyond"):
            unique_keys(np.array([[1, 2, 3], bad]))


def _reference_pyramid(bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # blocks of QUAD_BLOCK x QUAD_BLOCK quads, then 2 x 2 nodes per level up to one node
    free = [bounds[..., 0].astype(np.float64)]
    reach = [bounds[..., 1].astype(np.float64)]
    step = QUAD_BLOCK
    while True:
        for levels, pad, fold in ((free, np.inf, np.min), (reach, -np.inf, np.max)):
            a = levels[-1]
            rows, cols = -(-a.shape[0] // step), -(-a.shape[1] // step)
            padded = np.full((rows * step, cols * step), pad)
            padded[: a.shape[0], : a.shape[1]] = a
            levels.append(fold(padded.reshape(rows, step, cols, step), axis=(1, 3)))
        step = 2
        if free[-1].size == 1:
            break
    return (
        np.concatenate([a.ravel() for a in free[1:]]),
        np.concatenate([a.ravel() for a in reach[1:]]),
    )


@pytest.mark.parametrize("sensor", ["pinhole_z", "spherical"])
def test_a_prepared_scan_builds_its_tile_statistics_with_its_first_bounds(sensor: str) -> None:
    # mapping allocation needs no pyramid; the fusion pass computes the bounds, and the
    # pyramid with them (in partial blocks too: 47 x 39 quads, and a wrapping 180 x 23)
    _, scan = scenes.scans(sensor, 1)[0]
    prepared = prepare_scan(scan, _params(max_discontinuity=0.3))
    tiles_touched(prepared, GridSpec(0.05, 8, "mapping"))
    assert not prepared.has_pyramid
    bounds = prepared.quad_bounds().copy()
    assert prepared.has_pyramid
    free, reach, levels = first = prepared.pyramid()
    assert np.array_equal(prepared.quad_bounds(), bounds)
    assert prepared.pyramid() is first
    expected_free, expected_reach = _reference_pyramid(bounds)
    assert np.array_equal(free, expected_free)
    assert np.array_equal(reach, expected_reach)
    assert levels[-1, 1] * levels[-1, 2] == 1
    assert prepared.reach_max == reach[-1] == bounds[..., 1].max()
    assert np.isfinite(bounds[..., 0]).any() and np.isinf(bounds[..., 0]).any()


_LAYER_PROBE = """
import warnings
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
from rangefuse.engine.synth import make_dataset
data = make_dataset("room", views=2)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for _ in range(2):
        Volume(GridSpec(0.08, 8, "mapping"), FusionParams(NoiseModel(eps=0.1))).add_many(
            data.scans
        )
print(sum("workqueue" in str(w.message) for w in caught))
"""


@pytest.mark.parametrize(
    ("env", "warnings_expected"),
    [
        # numba tries its layers in this order: workqueue first stands for a machine
        # without OpenMP or TBB, where numba falls back to it silently
        ({"NUMBA_THREADING_LAYER_PRIORITY": "workqueue tbb omp"}, 1),
        ({"NUMBA_THREADING_LAYER": "workqueue"}, 0),  # asked for: no warning
        ({"NUMBA_THREADING_LAYER_PRIORITY": "workqueue tbb omp", "NUMBA_NUM_THREADS": "1"}, 0),
    ],
)
def test_fusion_warns_once_when_numba_falls_back_to_its_slow_threading_layer(
    env: dict[str, str], warnings_expected: int
) -> None:
    done = subprocess.run(
        [sys.executable, "-c", _LAYER_PROBE],
        env={**os.environ, "NUMBA_NUM_THREADS": "2", **env},
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert int(done.stdout.split()[-1]) == warnings_expected
