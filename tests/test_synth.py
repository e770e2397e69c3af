"""Synthetic scenes: exact ray casting and distances, rendering, noise, datasets."""

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
    Scan,
    SphericalSensor,
)
from rangefuse.engine.synth import (
    SCENES,
    AnalyticScene,
    NoiseSpec,
    SceneBuilder,
    SyntheticDataset,
    apply_noise,
    make_dataset,
    parse_noise,
    render,
)

# --- fixtures: one small dataset per scene, the room's full loop -------------------------------


@pytest.fixture(scope="module")
def datasets() -> dict[str, SyntheticDataset]:
    return {
        "object": make_dataset("object", views=3),
        "room": make_dataset("room", views=3),
        "street": make_dataset("street", views=2),
    }


@pytest.fixture(scope="module")
def room_loop() -> SyntheticDataset:
    return make_dataset("room")


def to_world(T: np.ndarray, p_S: np.ndarray) -> np.ndarray:
    return p_S @ T[:3, :3].T + T[:3, 3]


def surface_points(scan: Scan) -> np.ndarray:
    """World points of the finite pixels, unprojected in the sensor's range convention."""
    v, u = np.nonzero(np.isfinite(scan.range_m))
    p_S = scan.sensor.unproject(u, v, scan.range_m[v, u].astype(np.float64))
    return to_world(scan.T_W_S, p_S)


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
