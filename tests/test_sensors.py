"""Sensor models: validation, project/unproject round trips, kernels against the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rangefuse.engine import (
    InvalidSensorError,
    OrthographicSensor,
    PinholeSensor,
    Sensor,
    SphericalSensor,
    sensor_from_dict,
)

from tests import reference

PINHOLE = dict(
    model="pinhole",
    width=64,
    height=48,
    fx=60.0,
    fy=55.0,
    cx=31.5,
    cy=23.5,
    range_convention="ray",
    min_range=0.1,
    max_range=10.0,
)
SPHERICAL = dict(
    model="spherical",
    width=90,
    height=16,
    az_min=-math.pi,
    az_max=math.pi,
    el_min=-0.4,
    el_max=0.1,
    wrap=True,
    range_convention="ray",
    min_range=0.5,
    max_range=80.0,
)
SPHERICAL_TABLE = dict(
    model="spherical",
    width=60,
    height=8,
    az_min=-1.0,
    az_max=1.5,
    elevations=[0.2, 0.1, 0.05, 0.0, -0.03, -0.1, -0.2, -0.35],
    wrap=False,
    max_range=50.0,
)
CYLINDRICAL = dict(
    model="cylindrical",
    width=120,
    height=40,
    az_min=-math.pi,
    az_max=math.pi,
    wrap=True,
    fy=30.0,
    cy=19.5,
    range_convention="ray",
    max_range=20.0,
)
LINESCAN = dict(
    model="cylindrical",
    width=50,
    height=60,
    az_min=-0.3,
    az_max=0.25,
    wrap=False,
    fy=200.0,
    cy=29.5,
    axial="linear",
    range_convention="radial",
    max_range=3.0,
)
ORTHO = dict(
    model="orthographic", width=40, height=30, sx=0.01, sy=0.012, cx=19.5, cy=14.5, max_range=5.0
)
ALL = {
    "pinhole": PINHOLE,
    "pinhole_z": {**PINHOLE, "range_convention": "z"},
    "spherical": SPHERICAL,
    "spherical_table": SPHERICAL_TABLE,
    "cylindrical": CYLINDRICAL,
    "cylindrical_radial": {**CYLINDRICAL, "range_convention": "radial"},
    "linescan": LINESCAN,
    "orthographic": ORTHO,
}


def _pixels(sensor: Sensor, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    W, H = sensor.width, sensor.height
    u = rng.uniform(0, W - 1, n)
    v = rng.uniform(0, H - 1, n)
    d = rng.uniform(0.2, 0.9 * sensor.max_range, n)
    return u, v, d


@pytest.mark.parametrize("name", sorted(ALL))
def test_dict_round_trip(name: str) -> None:
    sensor = sensor_from_dict(ALL[name])
    assert sensor_from_dict(sensor.to_dict()) == sensor
    assert sensor.to_dict()["model"] == ALL[name]["model"]


@pytest.mark.parametrize("name", sorted(ALL))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unproject_then_project(name: str, seed: int) -> None:
    sensor = sensor_from_dict(ALL[name])
    u, v, d = _pixels(sensor, 500, seed)
    p = sensor.unproject(u, v, d)
    u2, v2, d2 = sensor.project(p)
    np.testing.assert_allclose(u2, u, atol=1e-9)
    np.testing.assert_allclose(v2, v, atol=1e-9)
    np.testing.assert_allclose(d2, d, rtol=1e-12, atol=1e-12)
    assert np.all(sensor.in_image(u2, v2))


@pytest.mark.parametrize("name", sorted(ALL))
def test_project_then_unproject(name: str) -> None:
    sensor = sensor_from_dict(ALL[name])
    u, v, d = _pixels(sensor, 500, 7)
    p = sensor.unproject(u, v, d)
    u2, v2, d2 = sensor.project(p)
    np.testing.assert_allclose(sensor.unproject(u2, v2, d2), p, atol=1e-9)


@pytest.mark.parametrize("name", sorted(ALL))
def test_kernel_projection_matches_reference(name: str) -> None:
    sensor = sensor_from_dict(ALL[name])
    rng = np.random.default_rng(3)
    p = rng.normal(size=(2000, 3)) * 3.0
    u, v, d = sensor.project(p)
    ru, rv, rd = reference.project(sensor.to_dict(), p)
    assert np.array_equal(np.isnan(u), np.isnan(ru))
    ok = ~np.isnan(u)
    inside = sensor.in_image(u[ok], v[ok])
    np.testing.assert_allclose(u[ok], ru[ok], atol=1e-9)
    np.testing.assert_allclose(d[ok], rd[ok], rtol=1e-12)
    # rows agree where the point is in the image (the reference clamps table rows outside)
    np.testing.assert_allclose(v[ok][inside], rv[ok][inside], atol=1e-9)


@pytest.mark.parametrize("name", sorted(ALL))
def test_a_pixels_points_are_evenly_spaced_in_range(name: str) -> None:
    # allocation (engine.allocation._slab_tiles) steps slab corners along a pixel's points
    sensor = sensor_from_dict(ALL[name])
    u, v, d = _pixels(sensor, 300, 11)
    d = 0.5 * sensor.max_range + 0.4 * d
    near, mid, far = (sensor.unproject(u, v, s * d) for s in (0.5, 0.75, 1.0))
    np.testing.assert_allclose(mid, 0.5 * (near + far), rtol=0.0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    fx=st.floats(10, 2000),
    fy=st.floats(10, 2000),
    x=st.floats(-5, 5),
    y=st.floats(-5, 5),
    z=st.floats(0.05, 20),
    conv=st.sampled_from(["ray", "z"]),
)
def test_pinhole_round_trip_property(fx, fy, x, y, z, conv) -> None:
    sensor = PinholeSensor(
        width=640,
        height=480,
        fx=fx,
        fy=fy,
        cx=319.5,
        cy=239.5,
        range_convention=conv,
        max_range=100.0,
    )
    p = np.array([[x, y, z]])
    u, v, d = sensor.project(p)
    np.testing.assert_allclose(sensor.unproject(u, v, d), p, rtol=1e-9, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(az=st.floats(-3.1, 3.1), el=st.floats(-1.4, 1.4), r=st.floats(0.1, 100))
def test_spherical_round_trip_property(az, el, r) -> None:
    sensor = SphericalSensor(
        width=2048,
        height=128,
        az_min=-math.pi,
        az_max=math.pi,
        el_min=-1.5,
        el_max=1.5,
        wrap=True,
        max_range=200.0,
    )
    p = r * np.array([[math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]])
    u, v, d = sensor.project(p)
    np.testing.assert_allclose(sensor.unproject(u, v, d), p, rtol=1e-9, atol=1e-9)


def test_known_values() -> None:
    pin = sensor_from_dict(PINHOLE)
    u, v, d = pin.project(np.array([0.0, 0.0, 2.0]))
    assert (float(u), float(v), float(d)) == (31.5, 23.5, 2.0)
    sph = sensor_from_dict(SPHERICAL)
    u, v, d = sph.project(np.array([0.0, 3.0, 0.0]))  # az = pi/2, el = 0
    daz = 2 * math.pi / 90
    assert float(u) == pytest.approx((math.pi / 2 + math.pi) / daz)
    assert float(v) == pytest.approx(0.1 / (0.5 / 15))
    assert float(d) == pytest.approx(3.0)
    line = sensor_from_dict(LINESCAN)
    u, v, d = line.project(np.array([1.2, 0.0, 0.05]))
    assert float(v) == pytest.approx(29.5 - 200.0 * 0.05)
    assert float(d) == pytest.approx(1.2)
    ortho = sensor_from_dict(ORTHO)
    u, v, d = ortho.project(np.array([0.1, -0.12, 3.0]))
    assert (float(u), float(v), float(d)) == pytest.approx((29.5, 4.5, 3.0))


def test_behind_and_on_axis_have_no_pixel() -> None:
    pin = sensor_from_dict(PINHOLE)
    assert np.isnan(pin.project(np.array([0.0, 0.0, -1.0]))[0])
    cyl = sensor_from_dict(CYLINDRICAL)
    assert np.isnan(cyl.project(np.array([0.0, 0.0, 1.0]))[0])
    ortho = sensor_from_dict(ORTHO)
    assert np.isnan(ortho.project(np.array([0.0, 0.0, -0.1]))[0])


def test_wrap_columns() -> None:
    sph = sensor_from_dict(SPHERICAL)
    # just below az_min + 2 pi: between the last column and the first
    az = math.pi - 1e-3
    u, v, _ = sph.project(np.array([math.cos(az), math.sin(az), 0.0]))
    assert 89.0 < float(u) < 90.0
    assert bool(sph.in_image(u, v))
    nowrap = sensor_from_dict({**SPHERICAL, "wrap": False})
    u, v, _ = nowrap.project(np.array([math.cos(az), math.sin(az), 0.0]))
    assert float(u) <= 89.0


def test_pixel_rays_are_unit_and_consistent() -> None:
    for spec in ALL.values():
        sensor = sensor_from_dict(spec)
        origin, direction = sensor.pixel_rays()
        assert origin.shape == (sensor.height, sensor.width, 3)
        np.testing.assert_allclose(np.linalg.norm(direction, axis=-1), 1.0, atol=1e-12)
        u, v, _ = sensor.project(origin + 1.5 * direction)
        vv, uu = np.mgrid[0 : sensor.height, 0 : sensor.width]
        np.testing.assert_allclose(u, uu, atol=1e-6)
        np.testing.assert_allclose(v, vv, atol=1e-6)


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"model": "fisheye"}, "sensor.model", "unknown sensor model 'fisheye'"),
        ({"fx": -1.0}, "sensor.fx", "must be > 0"),
        ({"fx": "wide"}, "sensor.fx", "must be a number"),
        ({"cx": float("nan")}, "sensor.cx", "must be finite"),
        ({"width": 1}, "sensor.width", "at least 2"),
        ({"width": 64.5}, "sensor.width", "integer"),
        ({"max_range": 0.05}, "sensor.max_range", "greater than min_range"),
        ({"min_range": -1.0}, "sensor.min_range", ">= 0"),
        ({"range_convention": "radial"}, "sensor.range_convention", "'ray', 'z'"),
        ({"focal": 3.0}, "sensor.focal", "unknown field"),
    ],
)
def test_invalid_pinhole(change: dict, field: str, words: str) -> None:
    with pytest.raises(InvalidSensorError) as info:
        sensor_from_dict({**PINHOLE, **change})
    assert str(info.value).startswith(field + ":")
    assert words in str(info.value)


@pytest.mark.parametrize(
    ("base", "change", "field", "words"),
    [
        (SPHERICAL, {"az_max": -4.0}, "sensor.az_max", "greater than az_min"),
        (SPHERICAL, {"az_max": 4.0, "az_min": -4.0}, "sensor.az_max", "more than a full turn"),
        (SPHERICAL, {"az_max": 1.0}, "sensor.wrap", "full turn"),
        (SPHERICAL, {"wrap": "yes"}, "sensor.wrap", "true or false"),
        (SPHERICAL, {"el_min": 0.5}, "sensor.el_max", "el_min < el_max"),
        (SPHERICAL_TABLE, {"elevations": [0.1] * 8}, "sensor.elevations", "decreasing"),
        (SPHERICAL_TABLE, {"elevations": [0.1, 0.0]}, "sensor.elevations", "one angle per row"),
        (SPHERICAL_TABLE, {"range_convention": "z"}, "sensor.range_convention", "'ray'"),
        (CYLINDRICAL, {"axial": "bent"}, "sensor.axial", "'perspective' or 'linear'"),
        (CYLINDRICAL, {"axial": "linear"}, "sensor.range_convention", "radial"),
        (CYLINDRICAL, {"fy": 0.0}, "sensor.fy", "> 0"),
        (ORTHO, {"sx": 0.0}, "sensor.sx", "> 0"),
        (ORTHO, {"range_convention": "ray"}, "sensor.range_convention", "'z'"),
    ],
)
def test_invalid_other_models(base: dict, change: dict, field: str, words: str) -> None:
    with pytest.raises(InvalidSensorError) as info:
        sensor_from_dict({**base, **change})
    assert str(info.value).startswith(field + ":"), str(info.value)
    assert words in str(info.value)


@pytest.mark.parametrize("model", [["pinhole"], {"a": 1}, 3, None])
def test_a_model_that_is_not_a_name_is_refused(model: object) -> None:
    with pytest.raises(InvalidSensorError, match=r"^sensor.model: unknown sensor model"):
        sensor_from_dict({**PINHOLE, "model": model})


def test_missing_fields_are_named() -> None:
    spec = dict(PINHOLE)
    del spec["fy"]
    with pytest.raises(InvalidSensorError, match=r"^sensor.fy: missing"):
        sensor_from_dict(spec)
    spec = dict(PINHOLE)
    del spec["range_convention"]
    with pytest.raises(InvalidSensorError, match=r"^sensor.range_convention: missing"):
        sensor_from_dict(spec)
    with pytest.raises(InvalidSensorError, match="JSON object"):
        sensor_from_dict(["pinhole"])  # type: ignore[arg-type]


def test_python_constructors() -> None:
    assert (
        OrthographicSensor(width=4, height=4, sx=1.0, sy=1.0, max_range=2.0).range_convention == "z"
    )
    with pytest.raises(InvalidSensorError, match="el_min and el_max"):
        SphericalSensor(width=4, height=4, max_range=2.0)
