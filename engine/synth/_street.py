"""The ``street`` scene: a street seen by a 64-beam spherical LiDAR driving along it.

Road, raised sidewalks and lots in ground tiles; buildings with window sills, entrance steps
and balconies; parked cars, street lights and trees, all placed by a generator with a fixed
seed, so that the street depends on its length only. The LiDAR drives along one lane 1.8 m
above the road, one scan every 2 m by default.
"""

from __future__ import annotations

import math

import numpy as np

from ..sensors import SphericalSensor
from ._builder import SceneBuilder, _pose, _rotation_z
from ._scene import AnalyticScene

_STREET_LIDAR_BEAMS = 64
_STREET_EL_MIN = -0.4363
_STREET_EL_MAX = 0.0349
#: Beam spacing grows linearly from the top beam to the bottom one (denser near the horizon).
_STREET_BEAM_SPACING_RATIO = 3.0


def _street_elevations() -> tuple[float, ...]:
    s = np.linspace(0.0, 1.0, _STREET_LIDAR_BEAMS)
    k = _STREET_BEAM_SPACING_RATIO - 1.0
    f = (s + 0.5 * k * s * s) / (1.0 + 0.5 * k)  # f' grows from 1 to the ratio
    return tuple(float(e) for e in _STREET_EL_MAX - (_STREET_EL_MAX - _STREET_EL_MIN) * f)


_STREET_LIDAR = SphericalSensor(
    width=1024,
    height=_STREET_LIDAR_BEAMS,
    az_min=-math.pi,
    az_max=math.pi,
    el_min=_STREET_EL_MIN,
    el_max=_STREET_EL_MAX,
    wrap=True,
    elevations=_street_elevations(),
    range_convention="ray",
    min_range=0.5,
    max_range=80.0,
)
_STREET_LENGTH_M = 40.0
_STREET_MAX_LENGTH_M = 10000.0
_STREET_SCAN_SPACING_M = 2.0
_STREET_SEED = 20240917  # fixed: the street depends on its length only
_STREET_BOUNDS_MARGIN_M = 0.5
_STREET_MARGIN_M = 15.0  # ground and buildings beyond both ends of the driven segment
_SENSOR_HEIGHT_M = 1.8
_SENSOR_LANE_Y_M = -1.5
_GROUND_TILE_M = 25.0
_GROUND_DEPTH_M = 0.3
_ROAD_HALF_WIDTH_M = 5.0  # two lanes and a parking strip each side
_PARKING_Y_M = 4.0
_CURB_HEIGHT_M = 0.15
_SIDEWALK_WIDTH_M = 3.0
_LOT_DEPTH_M = 14.0  # ground behind the sidewalk, under the buildings
_BUILDING_WIDTH_M = (6.0, 16.0)
_BUILDING_GAP_M = (2.0, 6.0)
_BUILDING_GAP_PROBABILITY = 0.35
_BUILDING_DEPTH_M = (8.0, 12.0)
_BUILDING_SETBACK_M = (0.0, 1.0)
_FLOOR_HEIGHT_M = 3.0
_FLOORS = (2, 7)  # inclusive range
_WINDOW_SPACING_M = 2.5
_SILL_SIZE_M = (1.2, 0.1, 0.06)  # along the facade, protrusion, height
_SILL_HEIGHT_M = 0.9  # above the floor
_STEP_SIZE_M = (1.8, 0.6, 0.3)  # entrance step
_BALCONY_PROBABILITY = 0.4
_BALCONY_SIZE_M = (2.4, 1.0, 0.15)
_RAILING_HEIGHT_M = 1.0
_CAR_SPACING_M = (5.5, 12.0)
_CAR_PROBABILITY = 0.7
_CAR_BODY_M = (4.3, 1.8, 0.75)
_CAR_CABIN_M = (2.2, 1.6, 0.5)
_CAR_CLEARANCE_M = 0.25
_WHEEL_RADIUS_M = 0.32
_POLE_SPACING_M = (18.0, 28.0)
_POLE_HEIGHT_M = 6.5
_POLE_RADIUS_M = 0.08
_TREE_SPACING_M = (8.0, 16.0)
_TREE_TRUNK_M = (2.5, 3.5)  # height
_TREE_CROWN_M = (1.2, 2.2)  # radius
_TREE_POLE_CLEARANCE_M = 2.0


def _street_scene(length_m: float) -> AnalyticScene:
    rng = np.random.default_rng(_STREET_SEED)
    b = SceneBuilder()
    x0, x1 = -_STREET_MARGIN_M, length_m + _STREET_MARGIN_M
    lot_outer = _ROAD_HALF_WIDTH_M + _SIDEWALK_WIDTH_M + _LOT_DEPTH_M
    n_tiles = max(1, math.ceil((x1 - x0) / _GROUND_TILE_M))
    tile = (x1 - x0) / n_tiles
    for i in range(n_tiles):
        xc = x0 + (i + 0.5) * tile
        road_size = (tile, 2.0 * _ROAD_HALF_WIDTH_M, _GROUND_DEPTH_M)
        b.add_box((xc, 0.0, -0.5 * _GROUND_DEPTH_M), road_size)
        for side in (-1.0, 1.0):  # raised sidewalk and lots; the curb is its road-side face
            yc = side * 0.5 * (_ROAD_HALF_WIDTH_M + lot_outer)
            height = _GROUND_DEPTH_M + _CURB_HEIGHT_M
            b.add_box(
                (xc, yc, _CURB_HEIGHT_M - 0.5 * height),
                (tile, lot_outer - _ROAD_HALF_WIDTH_M, height),
            )
    facade_y = _ROAD_HALF_WIDTH_M + _SIDEWALK_WIDTH_M
    for side in (-1.0, 1.0):
        _street_buildings(b, rng, side, facade_y, x0, x1)
        _street_cars(b, rng, side, x0, x1)
        poles = _street_poles(b, rng, side, x0, x1)
        _street_trees(b, rng, side, x0, x1, poles)
    return b.build()


def _street_buildings(
    b: SceneBuilder, rng: np.random.Generator, side: float, facade_y: float, x0: float, x1: float
) -> None:
    x = x0
    while x < x1:
        if rng.random() < _BUILDING_GAP_PROBABILITY:
            x += rng.uniform(*_BUILDING_GAP_M)
        width = min(rng.uniform(*_BUILDING_WIDTH_M), x1 - x)
        if width < 2.0:
            break
        depth = rng.uniform(*_BUILDING_DEPTH_M)
        front = facade_y + rng.uniform(*_BUILDING_SETBACK_M)
        floors = int(rng.integers(_FLOORS[0], _FLOORS[1] + 1))
        height = floors * _FLOOR_HEIGHT_M
        xc = x + 0.5 * width
        b.add_box((xc, side * (front + 0.5 * depth), 0.5 * height), (width, depth, height))
        # Window sills on the two lowest floors (the LiDAR sees little higher up), an entrance
        # step in front of the door in the middle of the facade.
        n_windows = int((width - 1.0) // _WINDOW_SPACING_M)
        sill_l, sill_p, sill_h = _SILL_SIZE_M
        for floor in (0, 1):
            z = _CURB_HEIGHT_M + floor * _FLOOR_HEIGHT_M + _SILL_HEIGHT_M
            for w in range(n_windows):
                wx = xc + (w - 0.5 * (n_windows - 1)) * _WINDOW_SPACING_M
                if floor == 0 and abs(wx - xc) < 0.5 * _WINDOW_SPACING_M:
                    continue  # the door
                b.add_box((wx, side * (front - 0.5 * sill_p), z), (sill_l, sill_p, sill_h))
        step_l, step_p, step_h = _STEP_SIZE_M
        b.add_box(
            (xc, side * (front - 0.5 * step_p), _CURB_HEIGHT_M + 0.5 * step_h),
            (step_l, step_p, step_h),
        )
        # Balconies (slab and railing) on a random column of upper floors.
        if floors >= 3 and rng.random() < _BALCONY_PROBABILITY:
            bl, bp, bh = _BALCONY_SIZE_M
            bx = xc + rng.uniform(-0.5, 0.5) * max(width - bl - 1.0, 0.0)
            for floor in range(1, min(floors, 4)):
                z = _CURB_HEIGHT_M + floor * _FLOOR_HEIGHT_M
                b.add_box((bx, side * (front - 0.5 * bp), z + 0.5 * bh), (bl, bp, bh))
                b.add_box(
                    (bx, side * (front - bp + 0.025), z + bh + 0.5 * _RAILING_HEIGHT_M),
                    (bl, 0.05, _RAILING_HEIGHT_M),
                )
        x += width


def _street_cars(
    b: SceneBuilder, rng: np.random.Generator, side: float, x0: float, x1: float
) -> None:
    x = x0 + rng.uniform(0.0, _CAR_SPACING_M[1])
    length, width, body_h = _CAR_BODY_M
    while x < x1 - 0.5 * length:
        if rng.random() < _CAR_PROBABILITY:
            yaw = rng.uniform(-0.06, 0.06)
            R = _rotation_z(yaw)
            centre = np.array([x, side * _PARKING_Y_M, 0.0])
            body_z = _CAR_CLEARANCE_M + 0.5 * body_h
            b.add_box(centre + np.array([0.0, 0.0, body_z]), _CAR_BODY_M, yaw)
            cabin = R @ np.array([-0.2, 0.0, 0.0]) + (0.0, 0.0, body_z + 0.5 * body_h)
            b.add_box(centre + cabin + (0.0, 0.0, 0.5 * _CAR_CABIN_M[2]), _CAR_CABIN_M, yaw)
            for wx in (-1.35, 1.35):
                for wy in (-1.0, 1.0):
                    hub = centre + R @ np.array([wx, wy * 0.5 * width, _WHEEL_RADIUS_M])
                    inward = R @ np.array([0.0, -wy * 0.22, 0.0])
                    b.add_cylinder(hub, hub + inward, _WHEEL_RADIUS_M)
        x += rng.uniform(*_CAR_SPACING_M)


def _street_poles(
    b: SceneBuilder, rng: np.random.Generator, side: float, x0: float, x1: float
) -> list[float]:
    xs = []
    y = side * (_ROAD_HALF_WIDTH_M + 0.4)
    x = x0 + rng.uniform(0.0, _POLE_SPACING_M[0])
    while x < x1:
        xs.append(x)
        top = np.array([x, y, _POLE_HEIGHT_M])
        b.add_cylinder((x, y, 0.0), top, _POLE_RADIUS_M)
        head = top + np.array([0.0, -side * 1.5, 0.3])
        b.add_cylinder(top - (0.0, 0.0, 0.2), head, 0.04)
        b.add_box(head + np.array([0.0, side * 0.1, -0.05]), (0.25, 0.5, 0.12))
        x += rng.uniform(*_POLE_SPACING_M)
    return xs


def _street_trees(
    b: SceneBuilder,
    rng: np.random.Generator,
    side: float,
    x0: float,
    x1: float,
    poles: list[float],
) -> None:
    y = side * (_ROAD_HALF_WIDTH_M + 1.2)
    x = x0 + rng.uniform(0.0, _TREE_SPACING_M[0])
    while x < x1:
        if all(abs(x - p) > _TREE_POLE_CLEARANCE_M for p in poles):
            trunk = rng.uniform(*_TREE_TRUNK_M)
            crown = rng.uniform(*_TREE_CROWN_M)
            b.add_cylinder((x, y, 0.0), (x, y, trunk), rng.uniform(0.12, 0.2))
            b.add_sphere((x, y, trunk + 0.8 * crown), crown)
        x += rng.uniform(*_TREE_SPACING_M)


def _street_poses(views: int, length_m: float) -> list[np.ndarray]:
    step = length_m / views
    return [
        _pose(np.eye(3), ((k + 0.5) * step, _SENSOR_LANE_Y_M, _SENSOR_HEIGHT_M))
        for k in range(views)
    ]
