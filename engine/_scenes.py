"""The synthetic scenes of ``rangefuse synth``: a scene builder, three scenes and their poses.

:class:`SceneBuilder` collects solids into an :class:`~engine._raycast.AnalyticScene`. With it
this module builds the ``object`` (a robot arm), ``room`` (a furnished room) and ``street``
(a LiDAR street) scenes of :func:`engine.synth.make_dataset`, with each scene's sensor and
sensor poses. Geometry and poses are deterministic. The public names are re-exported by
:mod:`engine.synth`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from ._raycast import _BOX_COLUMNS, _CYLINDER_COLUMNS, _SPHERE_COLUMNS, AnalyticScene
from .sensors import PinholeSensor, SphericalSensor

# --- building scenes ---------------------------------------------------------------------------


def _rotation_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _frame_along(axis: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Rotation whose first column is ``axis`` and whose third leans towards ``up``."""
    x = np.asarray(axis, np.float64)
    x = x / np.linalg.norm(x)
    u = np.asarray(up, np.float64)
    if abs(float(x @ u)) > 0.99:
        u = np.array([1.0, 0.0, 0.0]) if abs(x[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = np.cross(u, x)
    y /= np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])


def _vector3(value: ArrayLike) -> list[float]:
    return [float(x) for x in np.asarray(value, np.float64).reshape(3)]


class SceneBuilder:
    """Collects solids and builds an :class:`AnalyticScene`; the ``add_*`` methods chain."""

    def __init__(self) -> None:
        self._boxes: list[list[float]] = []
        self._spheres: list[list[float]] = []
        self._cylinders: list[list[float]] = []

    def add_box(
        self, centre: ArrayLike, size: ArrayLike, rotation: ArrayLike | None = None
    ) -> SceneBuilder:
        """Add a box of full edge lengths ``size`` (metres) centred at ``centre``.

        ``rotation`` is None (axis-aligned), a yaw angle about world z (radians) or a 3x3
        rotation matrix box -> world.
        """
        if rotation is None:
            R = np.eye(3)
        elif np.ndim(rotation) == 0:
            R = _rotation_z(float(np.asarray(rotation)))
        else:
            R = np.asarray(rotation, np.float64).reshape(3, 3)
        half = 0.5 * np.asarray(size, np.float64)
        self._boxes.append([*_vector3(centre), *_vector3(half), *R.reshape(9).tolist()])
        return self

    def add_bar(self, a: ArrayLike, b: ArrayLike, width: float, height: float) -> SceneBuilder:
        """Add a box from ``a`` to ``b`` with cross-section ``width`` x ``height`` (height ~ z)."""
        pa = np.asarray(a, np.float64)
        pb = np.asarray(b, np.float64)
        length = float(np.linalg.norm(pb - pa))
        return self.add_box(0.5 * (pa + pb), (length, width, height), _frame_along(pb - pa))

    def add_sphere(self, centre: ArrayLike, radius: float) -> SceneBuilder:
        """Add a sphere (metres)."""
        self._spheres.append([*_vector3(centre), float(radius)])
        return self

    def add_cylinder(self, a: ArrayLike, b: ArrayLike, radius: float) -> SceneBuilder:
        """Add a capped cylinder with axis from ``a`` to ``b`` (metres)."""
        self._cylinders.append([*_vector3(a), *_vector3(b), float(radius)])
        return self

    def build(self, offset: ArrayLike = (0.0, 0.0, 0.0)) -> AnalyticScene:
        """The scene of all solids added so far, moved by ``offset`` (metres)."""
        shift = np.asarray(offset, np.float64)
        boxes = np.array(self._boxes, np.float64).reshape(-1, _BOX_COLUMNS)
        spheres = np.array(self._spheres, np.float64).reshape(-1, _SPHERE_COLUMNS)
        cylinders = np.array(self._cylinders, np.float64).reshape(-1, _CYLINDER_COLUMNS)
        boxes[:, 0:3] += shift
        spheres[:, 0:3] += shift
        cylinders[:, 0:3] += shift
        cylinders[:, 3:6] += shift
        return AnalyticScene(boxes=boxes, spheres=spheres, cylinders=cylinders)


# --- poses -------------------------------------------------------------------------------------


def _pose(R: np.ndarray, t: ArrayLike) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_W_S`` of an OpenCV camera (x right, y down, z forward) at ``position`` looking at
    ``target`` with world z up; near the poles the up vector falls back to world y."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0])
    if abs(float(forward @ up)) > 0.95:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)  # = cross(-up, forward): down x forward
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return _pose(np.column_stack([right, down, forward]), position)


def _yaw_pitch_camera(position: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """OpenCV camera looking along azimuth ``yaw`` and elevation ``pitch`` (radians)."""
    forward = np.array(
        [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)]
    )
    return _look_at(position, position + forward)


def _fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly even unit vectors (n, 3), from near +z to near -z."""
    index = np.arange(n) + 0.5
    z = 1.0 - 2.0 * index / n
    rho = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * np.arange(n)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


# --- scene 1: object ---------------------------------------------------------------------------

_OBJECT_VIEWS = 12
_OBJECT_CAMERA = PinholeSensor(
    width=640,
    height=480,
    fx=600.0,
    fy=600.0,
    cx=319.5,
    cy=239.5,
    range_convention="ray",
    min_range=0.1,
    max_range=6.0,
)
_OBJECT_ORBIT_RADIUS_M = 2.0
_OBJECT_BOUNDS_MARGIN_M = 0.05
# Robot manipulator, built with its base on z = 0 and then centred on the origin.
_BASE_RADIUS_M = 0.16
_BASE_HEIGHT_M = 0.06
_COLUMN_SIZE_M = (0.10, 0.10, 0.34)
_SHOULDER_RADIUS_M = 0.075
_UPPER_ARM_SECTION_M = (0.08, 0.07)
_ELBOW_RADIUS_M = 0.06
_FOREARM_RADIUS_M = 0.04
_WRIST_RADIUS_M = 0.045
_ARM_YAW = 0.35  # the arm's vertical plane, radians from +x
_ELBOW_IN_PLANE_M = (0.22, 0.66)  # (reach, height)
_WRIST_IN_PLANE_M = (0.50, 0.56)
_PALM_SIZE_M = (0.03, 0.12, 0.05)  # along the forearm, across, thickness
_FINGER_LENGTH_M = 0.09
_FINGER_THICKNESS_M = 0.012
_FINGER_HEIGHT_M = 0.03
_FINGER_GAP_M = 0.06
# A rectangular handle on the column's back: four bars around a see-through hole.
_HANDLE_REACH_M = 0.27  # from the column axis
_HANDLE_Z_M = (0.12, 0.34)
_HANDLE_BAR_M = 0.02
_HANDLE_DEPTH_M = 0.03


def _object_scene() -> AnalyticScene:
    b = SceneBuilder()
    b.add_cylinder((0.0, 0.0, 0.0), (0.0, 0.0, _BASE_HEIGHT_M), _BASE_RADIUS_M)
    column_top = _BASE_HEIGHT_M + _COLUMN_SIZE_M[2]
    b.add_box((0.0, 0.0, _BASE_HEIGHT_M + 0.5 * _COLUMN_SIZE_M[2]), _COLUMN_SIZE_M)
    shoulder = np.array([0.0, 0.0, column_top + 0.04])
    b.add_sphere(shoulder, _SHOULDER_RADIUS_M)
    plane = np.array([math.cos(_ARM_YAW), math.sin(_ARM_YAW), 0.0])
    elbow = plane * _ELBOW_IN_PLANE_M[0] + np.array([0.0, 0.0, _ELBOW_IN_PLANE_M[1]])
    wrist = plane * _WRIST_IN_PLANE_M[0] + np.array([0.0, 0.0, _WRIST_IN_PLANE_M[1]])
    b.add_bar(shoulder, elbow, *_UPPER_ARM_SECTION_M)
    b.add_sphere(elbow, _ELBOW_RADIUS_M)
    b.add_cylinder(elbow, wrist, _FOREARM_RADIUS_M)
    b.add_sphere(wrist, _WRIST_RADIUS_M)
    # Gripper: palm across the forearm's end, two thin fingers with a gap between them.
    R = _frame_along(wrist - elbow)  # x along the forearm, y across (horizontal), z ~ up
    along, across = R[:, 0], R[:, 1]
    palm = wrist + along * (_WRIST_RADIUS_M + 0.5 * _PALM_SIZE_M[0])
    b.add_box(palm, _PALM_SIZE_M, R)
    finger_offset = 0.5 * (_FINGER_GAP_M + _FINGER_THICKNESS_M)
    finger_centre = palm + along * 0.5 * (_PALM_SIZE_M[0] + _FINGER_LENGTH_M)
    finger_size = (_FINGER_LENGTH_M, _FINGER_THICKNESS_M, _FINGER_HEIGHT_M)
    for side in (-1.0, 1.0):
        b.add_box(finger_centre + side * finger_offset * across, finger_size, R)
    # Handle on the side away from the arm.
    back = -plane
    inner = 0.5 * _COLUMN_SIZE_M[0]
    z0, z1 = _HANDLE_Z_M
    bar, depth = _HANDLE_BAR_M, _HANDLE_DEPTH_M
    r_mid = 0.5 * (inner + _HANDLE_REACH_M)
    length = _HANDLE_REACH_M - inner
    yaw = _ARM_YAW + math.pi
    for z in (z0 + 0.5 * bar, z1 - 0.5 * bar):  # top and bottom bars
        b.add_box(back * r_mid + (0.0, 0.0, z), (length, depth, bar), yaw)
    for r in (inner + 0.5 * bar, _HANDLE_REACH_M - 0.5 * bar):  # the two uprights
        b.add_box(back * r + (0.0, 0.0, 0.5 * (z0 + z1)), (bar, depth, z1 - z0), yaw)
    bounds = np.array(b.build().bounds())
    return b.build(offset=-0.5 * (bounds[:3] + bounds[3:]))


def _object_poses(views: int, scene: AnalyticScene) -> list[np.ndarray]:
    bounds = np.array(scene.bounds())
    centre = 0.5 * (bounds[:3] + bounds[3:])
    directions = _fibonacci_sphere(views)
    return [_look_at(centre + _OBJECT_ORBIT_RADIUS_M * d, centre) for d in directions]


# --- scene 2: room -----------------------------------------------------------------------------

_ROOM_VIEWS = 100
_ROOM_CAMERA = PinholeSensor(
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
_ROOM_BOUNDS_MARGIN_M = 0.1
_ROOM_SIZE_M = (5.0, 4.0, 2.6)  # interior x, y, z; the floor is z = 0, the room centred on x, y
_WALL_M = 0.1  # thickness of floor, ceiling and walls, all outside the interior
_WINDOW_X_M = (-0.7, 0.7)  # in the +y wall
_WINDOW_Z_M = (0.9, 1.9)
_DOOR_Y_M = (-0.45, 0.45)  # in the +x wall
_DOOR_HEIGHT_M = 2.05
_PANE_M = 0.08  # thickness of the window pane and the door, set behind the wall (recessed)
# Camera loop: an ellipse around the room centre, looking across the room.
_LOOP_RADII_M = (1.25, 0.8)
_LOOP_HEIGHT_M = 1.5
_LOOP_HEIGHT_SWING_M = 0.15
_LOOP_YAW_SWING = 0.6  # radians either side of looking at the opposite side
_LOOP_PITCH = -0.32  # radians, mean
_LOOP_PITCH_SWING = 0.3


def _room_shell(b: SceneBuilder) -> None:
    sx, sy, sz = _ROOM_SIZE_M
    hx, hy, w = 0.5 * sx, 0.5 * sy, _WALL_M
    full_x, full_y, full_z = sx + 2 * w, sy + 2 * w, sz + 2 * w
    b.add_box((0.0, 0.0, -0.5 * w), (full_x, full_y, w))  # floor
    b.add_box((0.0, 0.0, sz + 0.5 * w), (full_x, full_y, w))  # ceiling
    b.add_box((-hx - 0.5 * w, 0.0, 0.5 * sz), (w, full_y, full_z))  # -x wall
    b.add_box((0.0, -hy - 0.5 * w, 0.5 * sz), (full_x, w, full_z))  # -y wall
    # +y wall around a window opening; the pane is recessed behind it.
    (wx0, wx1), (wz0, wz1) = _WINDOW_X_M, _WINDOW_Z_M
    y_wall = hy + 0.5 * w
    left, right = wx0 - (-hx - w), (hx + w) - wx1
    b.add_box((-hx - w + 0.5 * left, y_wall, 0.5 * sz), (left, w, full_z))
    b.add_box((wx1 + 0.5 * right, y_wall, 0.5 * sz), (right, w, full_z))
    b.add_box((0.5 * (wx0 + wx1), y_wall, 0.5 * (wz0 - w)), (wx1 - wx0, w, wz0 + w))
    b.add_box((0.5 * (wx0 + wx1), y_wall, 0.5 * (wz1 + sz + w)), (wx1 - wx0, w, sz + w - wz1))
    b.add_box(
        (0.0, hy + w + 0.5 * _PANE_M, 0.5 * (wz0 + wz1)),
        (wx1 - wx0 + 0.2, _PANE_M, wz1 - wz0 + 0.2),
    )
    # +x wall around a door opening; the door is recessed behind it.
    (dy0, dy1), dz = _DOOR_Y_M, _DOOR_HEIGHT_M
    x_wall = hx + 0.5 * w
    front, rear = dy0 - (-hy - w), (hy + w) - dy1
    b.add_box((x_wall, -hy - w + 0.5 * front, 0.5 * sz), (w, front, full_z))
    b.add_box((x_wall, dy1 + 0.5 * rear, 0.5 * sz), (w, rear, full_z))
    b.add_box((x_wall, 0.5 * (dy0 + dy1), 0.5 * (dz + sz + w)), (w, dy1 - dy0, sz + w - dz))
    b.add_box(
        (hx + w + 0.5 * _PANE_M, 0.5 * (dy0 + dy1), 0.5 * dz), (_PANE_M, dy1 - dy0 + 0.2, dz + 0.2)
    )


def _table(b: SceneBuilder, x: float, y: float, size: tuple[float, float], height: float) -> None:
    top, leg = 0.04, 0.05
    b.add_box((x, y, height - 0.5 * top), (size[0], size[1], top))
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            lx = x + sx * (0.5 * size[0] - 0.06)
            ly = y + sy * (0.5 * size[1] - 0.06)
            b.add_box((lx, ly, 0.5 * (height - top)), (leg, leg, height - top))


def _chair(b: SceneBuilder, x: float, y: float, yaw: float) -> None:
    seat, seat_h, back_h, thick, leg_r = 0.44, 0.45, 0.45, 0.04, 0.018
    R = _rotation_z(yaw)
    b.add_box((x, y, seat_h - 0.5 * thick), (seat, seat, thick), yaw)
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            p = np.array([x, y, 0.0]) + R @ np.array([sx * 0.19, sy * 0.19, 0.0])
            b.add_cylinder(p, p + np.array([0.0, 0.0, seat_h - thick]), leg_r)
    back = np.array([x, y, seat_h + 0.5 * back_h]) + R @ np.array([-0.5 * seat + 0.02, 0, 0])
    b.add_box(back, (thick, seat, back_h), yaw)


def _room_scene() -> AnalyticScene:
    b = SceneBuilder()
    _room_shell(b)
    hx, hy = 0.5 * _ROOM_SIZE_M[0], 0.5 * _ROOM_SIZE_M[1]
    # Table with two chairs, a thin rug under them.
    b.add_box((0.4, -0.1, 0.005), (2.0, 1.4, 0.01))
    _table(b, 0.4, -0.1, (1.2, 0.8), 0.76)
    _chair(b, -0.45, -0.1, 0.0)
    _chair(b, 0.4, 0.65, -0.5 * math.pi)
    # Shelf against the -x wall: two sides, a back and four boards.
    depth, width, height, board = 0.35, 1.0, 1.8, 0.02
    x0, yc = -hx, 0.6
    xc = x0 + 0.5 * depth
    for s in (-1.0, 1.0):
        b.add_box((xc, yc + s * (0.5 * width - 0.5 * board), 0.5 * height), (depth, board, height))
    b.add_box((x0 + 0.5 * board, yc, 0.5 * height), (board, width, height))
    for z in (0.05, 0.6, 1.2, height - 0.5 * board):
        b.add_box((xc, yc, z), (depth, width - 2 * board, board))
    # Sofa against the -y wall: seat block, back rest, two arm rests.
    sofa_x, sofa_w, sofa_d = -0.7, 2.0, 0.85
    b.add_box((sofa_x, -hy + 0.5 * sofa_d, 0.21), (sofa_w, sofa_d, 0.42))
    b.add_box((sofa_x, -hy + 0.1, 0.62), (sofa_w, 0.2, 0.4))
    for s in (-1.0, 1.0):
        b.add_box(
            (sofa_x + s * (0.5 * sofa_w - 0.1), -hy + 0.5 * sofa_d, 0.53), (0.2, sofa_d, 0.22)
        )
    # A low cabinet by the door, rotated, with a ball next to it.
    b.add_box((1.9, -1.45, 0.3), (0.8, 0.45, 0.6), 0.4)
    b.add_sphere((1.55, 0.9, 0.12), 0.12)
    # Floor lamp in a corner: base, pole, spherical shade.
    lamp = (hx - 0.35, hy - 0.35)
    b.add_cylinder((*lamp, 0.0), (*lamp, 0.03), 0.15)
    b.add_cylinder((*lamp, 0.03), (*lamp, 1.55), 0.015)
    b.add_sphere((*lamp, 1.6), 0.18)
    return b.build()


def _room_poses(views: int) -> list[np.ndarray]:
    poses = []
    for k in range(views):
        angle = 2.0 * math.pi * k / views
        position = np.array(
            [
                _LOOP_RADII_M[0] * math.cos(angle),
                _LOOP_RADII_M[1] * math.sin(angle),
                _LOOP_HEIGHT_M + _LOOP_HEIGHT_SWING_M * math.sin(2.0 * angle),
            ]
        )
        yaw = angle + math.pi + _LOOP_YAW_SWING * math.sin(3.0 * angle)
        pitch = _LOOP_PITCH + _LOOP_PITCH_SWING * math.sin(5.0 * angle)
        poses.append(_yaw_pitch_camera(position, yaw, pitch))
    return poses


# --- scene 3: street ---------------------------------------------------------------------------

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
