"""Building scenes and placing sensors: :class:`SceneBuilder` and the pose helpers.

:class:`SceneBuilder` collects solids (boxes, bars, spheres, capped cylinders) and builds an
:class:`~._scene.AnalyticScene`; the pose helpers give sensor-to-world poses ``T_W_S`` of
OpenCV cameras (x right, y down, z forward) looking at a point or along a direction. The three
scenes (:mod:`._object`, :mod:`._room`, :mod:`._street`) are built with them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from ._scene import AnalyticScene
from ._solids import _BOX_COLUMNS, _CYLINDER_COLUMNS, _SPHERE_COLUMNS

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
