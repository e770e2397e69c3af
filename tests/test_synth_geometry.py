"""Synthetic scenes: exact ray casting and signed distances of the solids, and rendering."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rangefuse.engine import (
    InvalidInputError,
    OrthographicSensor,
    PinholeSensor,
    SphericalSensor,
)
from rangefuse.engine.synth import (
    SCENES,
    AnalyticScene,
    SceneBuilder,
    SyntheticDataset,
    render,
)

from tests.synth_helpers import surface_points, to_world

# --- fixtures: one small dataset per scene -----------------------------------------------------


def random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def random_rays(name: str, data: SyntheticDataset, rng: np.random.Generator, n: int):
    scene = data.scene
    lo, hi = np.array(data.bounds[:3]), np.array(data.bounds[3:])
    if name == "object":
        centre = 0.5 * (lo + hi)
        origins = centre + 1.2 * random_unit(rng, n)
        directions = rng.uniform(lo, hi, (n, 3)) - origins
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    else:
        if name == "room":
            origins = rng.uniform(lo, hi, (4 * n, 3))
        else:
            sensors = np.array([scan.T_W_S[:3, 3] for _, scan in data.scans])
            origins = sensors[rng.integers(len(sensors), size=4 * n)]
            origins += rng.uniform((-20.0, -3.0, -1.5), (20.0, 3.0, 3.0), (4 * n, 3))
        origins = origins[scene.signed_distance(origins) > 0.01][:n]
        directions = random_unit(rng, len(origins))
    return origins, directions


# --- exact geometry ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCENES)
def test_cast_hits_lie_on_the_surface(datasets, name):
    data = datasets[name]
    origins, directions = random_rays(name, data, np.random.default_rng(1), 3000)
    t = data.scene.cast(origins, directions)
    hit = np.isfinite(t)
    assert hit.mean() > 0.15
    assert np.all(t[hit] >= 0.0)
    p = origins[hit] + t[hit, None] * directions[hit]
    assert np.max(np.abs(data.scene.signed_distance(p))) < 1e-6
    ahead = t[hit] > 1e-3
    before = origins[hit][ahead] + (t[hit][ahead, None] - 1e-3) * directions[hit][ahead]
    assert np.all(data.scene.signed_distance(before) > 0.0)
    # The distance to the scene bounds the distance along any ray.
    assert np.all(data.scene.signed_distance(origins) <= t + 1e-9)


def test_sphere_analytic():
    scene = SceneBuilder().add_sphere((1.0, 2.0, 3.0), 0.5).build()
    origins = np.array([[1.0, 2.0, 0.0], [1.0, 2.6, 0.0], [1.0, 2.0, 3.2], [1.0, 2.0, 5.0]])
    up = np.array([[0.0, 0.0, 1.0]] * 4)
    t = scene.cast(origins, up)
    assert t[0] == pytest.approx(2.5, abs=1e-12)  # distance to the centre minus the radius
    assert t[1] == math.inf  # passes beside it
    assert t[2] == 0.0  # starts inside
    assert t[3] == math.inf  # the sphere is behind the ray
    sd = scene.signed_distance(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 5.0], [1.3, 2.4, 3.0]]))
    np.testing.assert_allclose(sd, [-0.5, 1.5, 0.0], atol=1e-12)


def test_rotated_box_analytic():
    yaw = 0.3
    scene = SceneBuilder().add_box((1.0, -1.0, 0.5), (0.4, 0.2, 1.0), yaw).build()
    axis = np.array([math.cos(yaw), math.sin(yaw), 0.0])  # the box's x axis
    side = np.array([-math.sin(yaw), math.cos(yaw), 0.0])  # its y axis
    centre = np.array([1.0, -1.0, 0.5])
    origins = np.array([centre - 3.0 * axis, centre - 3.0 * side, centre + 0.15 * side - axis])
    directions = np.array([axis, side, axis])
    t = scene.cast(origins, directions)
    np.testing.assert_allclose(t, [2.8, 2.9, math.inf], atol=1e-12)
    # Exact distances: to a face, to an edge, to a corner, inside.
    points = np.array(
        [
            centre + 0.7 * axis,
            centre + 0.5 * axis + 0.4 * side,
            centre + 0.5 * axis + 0.4 * side + np.array([0.0, 0.0, 1.0]),
            centre + 0.05 * side,
        ]
    )
    expected = [0.5, math.hypot(0.3, 0.3), math.sqrt(0.3**2 + 0.3**2 + 0.5**2), -0.05]
    np.testing.assert_allclose(scene.signed_distance(points), expected, atol=1e-12)
    assert scene.bounds() == pytest.approx(
        (
            1.0 - 0.2 * math.cos(yaw) - 0.1 * math.sin(yaw),
            -1.0 - 0.2 * math.sin(yaw) - 0.1 * math.cos(yaw),
            0.0,
            1.0 + 0.2 * math.cos(yaw) + 0.1 * math.sin(yaw),
            -1.0 + 0.2 * math.sin(yaw) + 0.1 * math.cos(yaw),
            1.0,
        ),
        abs=1e-12,
    )


def test_capped_cylinder_analytic():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)  # 1 m long
    scene = SceneBuilder().add_cylinder(a, b, 0.2).build()
    w = b - a
    n = np.array([0.0, 0.0, 1.0])
    origins = np.array([a - 2.0 * w, 0.5 * w - 3.0 * n, a - 2.0 * w + 0.25 * n, 0.5 * w])
    directions = np.array([w, n, w, n])
    t = scene.cast(origins, directions)
    np.testing.assert_allclose(t, [2.0, 2.8, math.inf, 0.0], atol=1e-12)
    points = np.array([0.5 * w + 0.5 * n, b + 0.3 * w, b + 0.3 * w + 0.5 * n, 0.5 * w + 0.05 * n])
    expected = [0.3, 0.3, math.hypot(0.3, 0.3), -0.15]
    np.testing.assert_allclose(scene.signed_distance(points), expected, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    quaternion=st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: sum(x * x for x in q) > 0.1),
    half=st.tuples(*[st.floats(0.01, 1.0)] * 3),
    direction=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda d: sum(x * x for x in d) > 0.1),
    distance=st.floats(1.8, 10.0),
)
def test_any_box_is_hit_on_its_surface(quaternion, half, direction, distance):
    w, x, y, z = np.array(quaternion) / np.linalg.norm(quaternion)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    scene = SceneBuilder().add_box((0.1, 0.2, 0.3), 2.0 * np.array(half), R).build()
    d = np.array(direction) / np.linalg.norm(direction)
    origin = np.array([0.1, 0.2, 0.3]) - distance * d
    t = scene.cast(origin[None], d[None])[0]
    assert math.isfinite(t)  # aimed at the centre
    assert abs(scene.signed_distance((origin + t * d)[None])[0]) < 1e-9
    assert scene.signed_distance(origin[None])[0] <= t + 1e-12


def test_union_takes_the_first_entry_and_starts_inside_at_zero():
    scene = (
        SceneBuilder()
        .add_box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        .add_sphere((0.0, 0.0, 0.8), 0.5)
        .build()
    )
    origins = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, -5.0]])
    directions = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(scene.cast(origins, directions), [3.7, 0.0, 4.5], atol=1e-12)
    points = np.array([[0.0, 0.0, 0.75], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    np.testing.assert_allclose(scene.signed_distance(points), [-0.45, -0.5, 0.7], atol=1e-12)


def test_empty_scene_and_validation():
    empty = AnalyticScene()
    assert empty.cast(np.zeros((2, 3)), np.eye(3)[:2]).tolist() == [math.inf, math.inf]
    assert empty.signed_distance(np.zeros((1, 3)))[0] == math.inf
    with pytest.raises(InvalidInputError, match="scene: is empty"):
        empty.bounds()
    with pytest.raises(InvalidInputError, match=r"scene.spheres: must have shape \(n, 4\)"):
        AnalyticScene(spheres=np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match=r"scene.spheres: radii must be > 0"):
        AnalyticScene(spheres=[[0.0, 0.0, 0.0, -1.0]])
    with pytest.raises(InvalidInputError, match=r"scene.boxes: row 0: the rotation"):
        AnalyticScene(boxes=[[0.0] * 3 + [1.0] * 3 + [2.0, 0, 0, 0, 1, 0, 0, 0, 1]])
    with pytest.raises(InvalidInputError, match=r"scene.cylinders: end points"):
        AnalyticScene(cylinders=[[1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.1]])
    with pytest.raises(InvalidInputError, match="directions_W"):
        empty.cast(np.zeros((2, 3)), np.zeros((3, 3)))


def test_scene_dict_round_trip(datasets):
    scene = datasets["object"].scene
    again = AnalyticScene.from_dict(json.loads(json.dumps(scene.to_dict())))
    for name in ("boxes", "spheres", "cylinders"):
        np.testing.assert_array_equal(getattr(again, name), getattr(scene, name))
    with pytest.raises(InvalidInputError, match=r"scene.cubes: unknown field"):
        AnalyticScene.from_dict({"cubes": []})


# --- rendering ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCENES)
def test_render_points_lie_on_the_surface(datasets, name):
    data = datasets[name]
    for _, scan in data.scans:
        rng = scan.range_m
        finite = rng[np.isfinite(rng)]
        assert finite.size > 0.02 * rng.size
        assert np.all((finite >= scan.sensor.min_range) & (finite <= scan.sensor.max_range))
        points = surface_points(scan)
        # float32 ranges: about 1e-7 relative error.
        tolerance = 1e-5 if name != "street" else 2e-7 * scan.sensor.max_range
        assert np.max(np.abs(data.scene.signed_distance(points))) < tolerance


def test_background(datasets):
    object_maps = [scan.range_m for _, scan in datasets["object"].scans]
    assert all(np.isposinf(r).mean() > 0.5 for r in object_maps)  # no-return background
    assert not any(np.isnan(r).any() for r in object_maps)
    room_maps = [scan.range_m for _, scan in datasets["room"].scans]
    assert all(np.isfinite(r).all() for r in room_maps)  # a closed room
    street_maps = [scan.range_m for _, scan in datasets["street"].scans]
    assert all(np.isposinf(r).any() and np.isfinite(r).mean() > 0.5 for r in street_maps)


def test_render_honours_the_range_convention(datasets):
    data = datasets["room"]
    _, scan = data.scans[1]
    sensor = scan.sensor
    assert sensor.range_convention == "z"
    ray_sensor = dataclasses.replace(sensor, range_convention="ray")
    ray_range = render(data.scene, ray_sensor, scan.T_W_S)
    v, u = np.mgrid[0 : sensor.height, 0 : sensor.width]
    stretch = np.sqrt(((u - sensor.cx) / sensor.fx) ** 2 + ((v - sensor.cy) / sensor.fy) ** 2 + 1)
    np.testing.assert_allclose(ray_range, scan.range_m * stretch, rtol=1e-6)
    assert np.all(ray_range[0, 0] > scan.range_m[0, 0])


@pytest.mark.parametrize("name", ["room", "street"])
def test_render_matches_cast(datasets, name):
    # The fused kernel against the definition: cast in the world, project in the sensor frame.
    data = datasets[name]
    _, scan = data.scans[-1]
    sensor = scan.sensor
    origins_S, directions_S = (a.reshape(-1, 3) for a in sensor.pixel_rays())
    T = scan.T_W_S
    t = data.scene.cast(to_world(T, origins_S), directions_S @ T[:3, :3].T)
    d = np.full(t.shape, np.inf)
    hit = np.isfinite(t)
    d[hit] = sensor.project(origins_S[hit] + t[hit, None] * directions_S[hit])[2]
    d[d > sensor.max_range] = np.inf
    d[d < sensor.min_range] = np.nan
    expected = d.reshape(sensor.shape)
    for got in (render(data.scene, sensor, T), scan.range_m):
        np.testing.assert_array_equal(np.isposinf(got), np.isposinf(expected))
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
        np.testing.assert_allclose(got, expected, rtol=1e-7)


def test_min_and_max_range():
    builder = SceneBuilder().add_sphere((0.0, 0.0, 1.0), 0.5)
    scene = builder.add_sphere((0.0, 0.0, -9.0), 1.0).build()
    camera = PinholeSensor(
        width=8,
        height=6,
        fx=8.0,
        fy=8.0,
        cx=3.5,
        cy=2.5,
        range_convention="ray",
        min_range=0.6,
        max_range=5.0,
    )
    up = np.eye(4)  # looks along +z at the near sphere: 0.5 m < min_range
    assert np.isnan(render(scene, camera, up)[2:4, 3:5]).all()
    down = np.diag([1.0, -1.0, -1.0, 1.0])  # looks along -z: the far sphere is beyond max_range
    assert np.isposinf(render(scene, camera, down)).all()
    inside = np.eye(4)
    inside[:3, 3] = (0.0, 0.0, 1.0)
    assert np.isnan(render(scene, camera, inside)).all()  # t = 0 inside a solid: invalid


def test_render_other_sensor_models():
    scene = SceneBuilder().add_box((0.0, 0.0, -0.5), (40.0, 40.0, 1.0)).build()  # top at z = 0
    ortho = OrthographicSensor(width=4, height=3, sx=0.1, sy=0.1, cx=1.5, cy=1.0, max_range=10.0)
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[2, 3] = 2.0  # 2 m above, looking down
    np.testing.assert_allclose(render(scene, ortho, T), 2.0, rtol=1e-7)
    lidar = SphericalSensor(
        width=8,
        height=3,
        el_min=-0.6,
        el_max=-0.2,
        wrap=True,
        az_min=-math.pi,
        az_max=math.pi,
        max_range=50.0,
    )
    T = np.eye(4)
    T[2, 3] = 1.0
    expected = 1.0 / np.sin([0.2, 0.4, 0.6])
    np.testing.assert_allclose(
        render(scene, lidar, T), np.repeat(expected[:, None], 8, 1), rtol=1e-6
    )
    with pytest.raises(InvalidInputError, match="T_W_S"):
        render(scene, lidar, np.eye(3))
