"""Synthetic scenes: the three scenes, their noise and the datasets made of them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rangefuse.engine import InvalidInputError, PinholeSensor, Scan
from rangefuse.engine.synth import (
    AnalyticScene,
    NoiseSpec,
    SyntheticDataset,
    apply_noise,
    make_dataset,
    parse_noise,
)

from tests.synth_helpers import surface_points

# --- fixtures: one small dataset per scene, the room's full loop -------------------------------


@pytest.fixture(scope="module")
def room_loop() -> SyntheticDataset:
    return make_dataset("room")


# --- the three scenes --------------------------------------------------------------------------


def test_object_scene(datasets):
    data = datasets["object"]
    lo, hi = np.array(data.scene.bounds()[:3]), np.array(data.scene.bounds()[3:])
    extent = hi - lo
    assert 0.85 <= extent.max() <= 0.95
    np.testing.assert_allclose(0.5 * (lo + hi), 0.0, atol=0.05)  # centred near the origin
    assert np.all(np.array(data.bounds[:3]) < lo) and np.all(np.array(data.bounds[3:]) > hi)
    # Twelve cameras 2 m from the centre, from above and from below, looking at it.
    default = make_dataset("object")
    assert len(default.scans) == 12
    centre = 0.5 * (lo + hi)
    for _, scan in default.scans:
        T = scan.T_W_S
        assert np.linalg.norm(T[:3, 3] - centre) == pytest.approx(2.0)
        forward = T[:3, 2]
        np.testing.assert_allclose(forward, (centre - T[:3, 3]) / 2.0, atol=1e-12)
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    heights = [scan.T_W_S[2, 3] for _, scan in default.scans]
    assert min(heights) < -1.5 and max(heights) > 1.5


def test_object_has_thin_parts_and_a_hole(datasets):
    scene = datasets["object"].scene
    thickness_m = 2.0 * scene.boxes[:, 3:6].min(axis=1)
    assert np.sum((thickness_m >= 0.01) & (thickness_m <= 0.015)) >= 2  # the two fingers
    # Silhouette along y on a 2.5 mm grid: some misses are enclosed by hits (a hole to see
    # through), i.e. not connected to the border of the image.
    xs = np.arange(-0.6, 0.6, 0.0025)
    zs = np.arange(-0.5, 0.5, 0.0025)
    x, z = np.meshgrid(xs, zs, indexing="ij")
    origins = np.column_stack([x.ravel(), np.full(x.size, -2.0), z.ravel()])
    directions = np.tile([0.0, 1.0, 0.0], (x.size, 1))
    miss = ~np.isfinite(scene.cast(origins, directions)).reshape(x.shape)
    outside = np.zeros_like(miss)
    outside[0, :] = outside[-1, :] = outside[:, 0] = outside[:, -1] = True
    outside &= miss
    while True:
        grown = outside.copy()
        grown[1:] |= outside[:-1]
        grown[:-1] |= outside[1:]
        grown[:, 1:] |= outside[:, :-1]
        grown[:, :-1] |= outside[:, 1:]
        grown &= miss
        if np.array_equal(grown, outside):
            break
        outside = grown
    hole = miss & ~outside
    assert hole.sum() * 0.0025**2 > 0.005  # at least 50 cm^2


def test_room_scene(room_loop):
    data = room_loop
    assert len(data.scans) == 100
    lo, hi = np.array(data.scene.bounds()[:3]), np.array(data.scene.bounds()[3:])
    assert 5.0 < hi[0] - lo[0] < 5.5 and 4.0 < hi[1] - lo[1] < 4.5 and 2.6 < hi[2] - lo[2] < 3.0
    positions = np.array([scan.T_W_S[:3, 3] for _, scan in data.scans])
    assert np.all(data.scene.signed_distance(positions) > 0.05)  # always in free space
    assert np.all((positions[:, 2] > 1.3) & (positions[:, 2] < 1.7))
    step = np.linalg.norm(np.diff(positions, axis=0, append=positions[:1]), axis=1)
    assert step.max() < 0.15  # a closed loop of small steps
    # Consecutive frames overlap: most of one frame's points project into the next frame.
    sensor = data.sensor
    for k in range(0, 100, 7):
        points = surface_points(data.scans[k][1])[::50]
        T = data.scans[(k + 1) % 100][1].T_W_S
        p_S = (points - T[:3, 3]) @ T[:3, :3]
        u, v, _ = sensor.project(p_S)
        assert np.mean(sensor.in_image(u, v)) > 0.7
    # Over the loop every solid is seen (hidden table and chair legs aside).
    points = np.concatenate([surface_points(scan)[::31] for _, scan in data.scans])
    seen = 0
    for rows, kind in (
        (data.scene.boxes, "boxes"),
        (data.scene.spheres, "spheres"),
        (data.scene.cylinders, "cylinders"),
    ):
        for row in rows:
            solid = AnalyticScene(**{kind: row[None]})
            seen += bool(np.any(np.abs(solid.signed_distance(points)) < 1e-4))
    assert seen >= data.scene.n_solids - 3


def test_street_scene(datasets):
    data = datasets["street"]
    sensor = data.sensor
    assert sensor.shape == (64, 1024) and sensor.wrap and sensor.range_convention == "ray"
    steps = -np.diff(np.array(sensor.elevations))
    assert np.all(steps > 0.0)
    assert steps[0] < 0.6 * steps[-1]  # denser near the horizon
    assert sensor.elevations[0] == pytest.approx(0.0349) and sensor.el_min == pytest.approx(-0.4363)
    positions = np.array([scan.T_W_S[:3, 3] for _, scan in data.scans])
    assert np.all(data.scene.signed_distance(positions) > 0.05)
    np.testing.assert_allclose(positions[:, 2], 1.8)  # the road is at z = 0
    first, second = (scan.range_m for _, scan in data.scans)
    assert np.mean(first != second) > 0.5
    assert len(make_dataset("street").scans) == 20
    short = make_dataset("street", length_m=7.0)
    assert len(short.scans) == 4
    assert short.bounds[3] > 7.0 and short.bounds[0] < 0.0


def test_street_scales_with_length():
    small = make_dataset("street", views=1, length_m=50.0)
    large = make_dataset("street", views=1, length_m=1000.0)
    ratio = large.scene.n_solids / small.scene.n_solids
    assert 8.0 < ratio < 25.0  # linear in the length (1030 m / 80 m of ground)
    assert large.bounds[3] > 1000.0
    # The geometry depends on the length only.
    again = make_dataset("street", views=1, length_m=50.0, seed=7)
    np.testing.assert_array_equal(again.scene.boxes, small.scene.boxes)


# --- noise -------------------------------------------------------------------------------------


def test_parse_noise_valid():
    assert parse_noise("none") == NoiseSpec()
    assert parse_noise("") == NoiseSpec()
    spec = parse_noise(" gaussian:0.005, dropouts:0.05,background:nan ")
    assert spec == NoiseSpec(gaussian_m=0.005, dropouts=0.05, background="nan")
    spec = parse_noise("uniform:0.01,gaussian:0.002,spikes:0.001,dropouts:1,background:inf")
    assert spec == NoiseSpec(0.01, 0.002, 0.001, 1.0, "inf")
    assert parse_noise(spec.to_spec()) == spec
    assert NoiseSpec.from_dict(spec.to_dict()) == spec


@pytest.mark.parametrize(
    ("spec", "item", "problem"),
    [
        ("foo:1", "foo:1", "unknown kind"),
        ("uniform:0.01,blur:2", "blur:2", "unknown kind"),
        ("uniform:-0.1", "uniform:-0.1", ">= 0"),
        ("gaussian:-1e-3", "gaussian:-1e-3", ">= 0"),
        ("dropouts:1.5", "dropouts:1.5", "fraction"),
        ("spikes:-0.1", "spikes:-0.1", ">= 0"),
        ("gaussian:abc", "gaussian:abc", "not a number"),
        ("gaussian:nan", "gaussian:nan", "not a finite number"),
        ("uniform:0.1,uniform:0.2", "uniform:0.2", "twice"),
        ("uniform", "uniform", "needs a value"),
        ("background:zero", "background:zero", "inf or nan"),
        ("uniform:0.1,,spikes:0.1", "", "empty item"),
        ("none,uniform:0.1", "none", "unknown kind"),
    ],
)
def test_parse_noise_invalid(spec, item, problem):
    with pytest.raises(InvalidInputError) as info:
        parse_noise(spec)
    message = str(info.value)
    assert info.value.field == "noise"
    assert f"item {item!r}" in message and problem in message
    for kind in ("uniform", "gaussian", "spikes", "dropouts", "background"):
        assert kind in message


def test_noise_spec_validation():
    with pytest.raises(InvalidInputError, match=r"noise.spikes"):
        NoiseSpec(spikes=2.0)
    with pytest.raises(InvalidInputError, match=r"noise.background"):
        NoiseSpec(background="zero")
    with pytest.raises(InvalidInputError, match=r"noise.uniform_m"):
        NoiseSpec(uniform_m=-1.0)


CAMERA = PinholeSensor(
    width=640,
    height=480,
    fx=525.0,
    fy=525.0,
    cx=319.5,
    cy=239.5,
    range_convention="z",
    min_range=0.1,
    max_range=8.0,
)


def flat_map(value: float = 5.0) -> np.ndarray:
    return np.full(CAMERA.shape, value, np.float32)


def test_additive_noise_statistics():
    rng = np.random.default_rng(3)
    uniform = apply_noise(flat_map(), NoiseSpec(uniform_m=0.01), CAMERA, rng) - 5.0
    assert uniform.dtype == np.float32
    assert abs(uniform.mean()) < 1e-4
    assert uniform.std() == pytest.approx(0.01 / math.sqrt(3.0), rel=0.02)
    assert np.abs(uniform).max() <= 0.01 + 1e-6
    gaussian = apply_noise(flat_map(), NoiseSpec(gaussian_m=0.005), CAMERA, rng) - 5.0
    assert abs(gaussian.mean()) < 1e-4
    assert gaussian.std() == pytest.approx(0.005, rel=0.02)
    # Stays positive (at least min_range) however large the noise.
    wild = apply_noise(flat_map(0.2), NoiseSpec(gaussian_m=1.0), CAMERA, rng)
    assert wild.min() >= CAMERA.min_range
    Scan(range_m=wild, T_W_S=np.eye(4), sensor=CAMERA)


def test_spikes_dropouts_and_background():
    rng = np.random.default_rng(4)
    clean = flat_map()
    clean[:, :160] = np.inf  # a quarter of no-return pixels
    clean[0, 160:200] = np.nan
    n_valid = np.isfinite(clean).sum()
    spiky = apply_noise(clean, NoiseSpec(spikes=0.01), CAMERA, rng)
    changed = np.isfinite(spiky) & (np.abs(spiky - 5.0) > 1e-6)
    assert changed.sum() / n_valid == pytest.approx(0.01, rel=0.1)
    assert spiky[changed].min() >= CAMERA.min_range and spiky[changed].max() <= CAMERA.max_range
    assert np.isposinf(spiky[:, :160]).all() and np.isnan(spiky[0, 160:200]).all()
    dropped = apply_noise(clean, NoiseSpec(dropouts=0.05), CAMERA, rng)
    new_nan = np.isnan(dropped) & ~np.isnan(clean)
    assert new_nan.mean() == pytest.approx(0.05, rel=0.05)
    assert np.all(dropped[np.isfinite(dropped)] == 5.0)
    background = apply_noise(clean, NoiseSpec(background="nan"), CAMERA, rng)
    assert np.isnan(background[:, :160]).all() and not np.isinf(background).any()
    assert np.all(background[:, 200:] == 5.0)
    kept = apply_noise(clean, NoiseSpec(gaussian_m=0.01), CAMERA, rng)
    assert np.isposinf(kept[:, :160]).all()  # noise touches hits only


def test_noise_is_seeded():
    noise = parse_noise("gaussian:0.01,spikes:0.01,dropouts:0.01")
    a = make_dataset("object", views=1, noise=noise, seed=5).scans[0][1].range_m
    b = make_dataset("object", views=1, noise=noise, seed=5).scans[0][1].range_m
    c = make_dataset("object", views=1, noise=noise, seed=6).scans[0][1].range_m
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c, equal_nan=True)
    with_nan = make_dataset("object", views=1, noise=parse_noise("background:nan"))
    rng = with_nan.scans[0][1].range_m
    assert np.isnan(rng).mean() > 0.5 and not np.isinf(rng).any()


# --- datasets ----------------------------------------------------------------------------------


def test_make_dataset_is_deterministic(datasets):
    for name in ("object", "street"):
        again = make_dataset(name, views=len(datasets[name].scans), seed=123)
        assert [k for k, _ in again.scans] == [k for k, _ in datasets[name].scans]
        for (_, a), (_, b) in zip(again.scans, datasets[name].scans, strict=True):
            np.testing.assert_array_equal(a.range_m, b.range_m)
            np.testing.assert_array_equal(a.T_W_S, b.T_W_S)
    assert [k for k, _ in datasets["room"].scans] == ["scan_0000", "scan_0001", "scan_0002"]


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"name": "garden"}, "name"),
        ({"name": "room", "views": 0}, "views"),
        ({"name": "room", "views": 2.5}, "views"),
        ({"name": "object", "length_m": 10.0}, "length_m"),
        ({"name": "street", "length_m": -5.0}, "length_m"),
        ({"name": "street", "length_m": math.inf}, "length_m"),
        ({"name": "room", "noise": "gaussian:0.1"}, "noise"),
    ],
)
def test_make_dataset_rejects(kwargs, field):
    with pytest.raises(InvalidInputError) as info:
        make_dataset(**kwargs)
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")
