"""The solids of an analytic scene: their row layout, exact ray intervals and signed distances.

A scene is a union of convex solids, each one row of a float64 array: oriented boxes, spheres
and capped cylinders. This module fixes the rows' columns and kind codes, checks rows, and
holds the per-solid numba functions the hierarchy's kernels call (:mod:`._hierarchy`): the
interval ``[t_in, t_out]`` in which a ray is inside a solid, and the exact signed distance of
a point to it. It also gives each solid's axis-aligned box, from which the hierarchy is built.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from ..errors import InvalidInputError

_BOX_COLUMNS = 15  # centre(3), half extents(3), rotation box -> world, row-major (9)
_SPHERE_COLUMNS = 4  # centre(3), radius
_CYLINDER_COLUMNS = 7  # end point a(3), end point b(3), radius
_BOX = 0
_SPHERE = 1
_CYLINDER = 2
#: Largest deviation of ``R^T R`` from the identity accepted in a box rotation.
_ROTATION_TOLERANCE = 1e-6
#: Below this squared length of its off-axis part a ray runs parallel to a cylinder axis.
_PARALLEL_EPS = 1e-18

# --- ray intervals and signed distances (numba) ------------------------------------------------


@njit(cache=True)
def _box_interval(boxes, row, ox, oy, oz, dx, dy, dz):
    # Slab test in the box frame: x_B = R^T (x_W - c); column `axis` of R is that box axis.
    qx = ox - boxes[row, 0]
    qy = oy - boxes[row, 1]
    qz = oz - boxes[row, 2]
    t_in = -math.inf
    t_out = math.inf
    for axis in range(3):
        ax = boxes[row, 6 + axis]
        ay = boxes[row, 9 + axis]
        az = boxes[row, 12 + axis]
        o = ax * qx + ay * qy + az * qz
        d = ax * dx + ay * dy + az * dz
        h = boxes[row, 3 + axis]
        if d == 0.0:
            if o < -h or o > h:
                return math.inf, -math.inf
        else:
            t1 = (-h - o) / d
            t2 = (h - o) / d
            if t1 > t2:
                t1, t2 = t2, t1
            t_in = max(t_in, t1)
            t_out = min(t_out, t2)
    return t_in, t_out


@njit(cache=True)
def _sphere_interval(spheres, row, ox, oy, oz, dx, dy, dz):
    qx = ox - spheres[row, 0]
    qy = oy - spheres[row, 1]
    qz = oz - spheres[row, 2]
    r = spheres[row, 3]
    b = qx * dx + qy * dy + qz * dz
    c = qx * qx + qy * qy + qz * qz - r * r
    disc = b * b - c
    if disc < 0.0:
        return math.inf, -math.inf
    s = math.sqrt(disc)
    return -b - s, -b + s


@njit(cache=True)
def _cylinder_axis(cylinders, row):
    ax = cylinders[row, 3] - cylinders[row, 0]
    ay = cylinders[row, 4] - cylinders[row, 1]
    az = cylinders[row, 5] - cylinders[row, 2]
    length = math.sqrt(ax * ax + ay * ay + az * az)
    return ax / length, ay / length, az / length, length


@njit(cache=True)
def _cylinder_interval(cylinders, row, ox, oy, oz, dx, dy, dz):
    # Infinite cylinder |perp(o + t d)| <= r intersected with the slab 0 <= axial <= L.
    wx, wy, wz, length = _cylinder_axis(cylinders, row)
    r = cylinders[row, 6]
    qx = ox - cylinders[row, 0]
    qy = oy - cylinders[row, 1]
    qz = oz - cylinders[row, 2]
    q_axial = qx * wx + qy * wy + qz * wz
    d_axial = dx * wx + dy * wy + dz * wz
    px = qx - q_axial * wx
    py = qy - q_axial * wy
    pz = qz - q_axial * wz
    ex = dx - d_axial * wx
    ey = dy - d_axial * wy
    ez = dz - d_axial * wz
    a = ex * ex + ey * ey + ez * ez
    b = px * ex + py * ey + pz * ez
    c = px * px + py * py + pz * pz - r * r
    if a < _PARALLEL_EPS:
        if c > 0.0:
            return math.inf, -math.inf
        t_in = -math.inf
        t_out = math.inf
    else:
        disc = b * b - a * c
        if disc < 0.0:
            return math.inf, -math.inf
        s = math.sqrt(disc)
        t_in = (-b - s) / a
        t_out = (-b + s) / a
    if d_axial == 0.0:
        if q_axial < 0.0 or q_axial > length:
            return math.inf, -math.inf
    else:
        t1 = -q_axial / d_axial
        t2 = (length - q_axial) / d_axial
        if t1 > t2:
            t1, t2 = t2, t1
        t_in = max(t_in, t1)
        t_out = min(t_out, t2)
    return t_in, t_out


@njit(cache=True)
def _box_sdf(boxes, row, x, y, z):
    qx = x - boxes[row, 0]
    qy = y - boxes[row, 1]
    qz = z - boxes[row, 2]
    outside2 = 0.0
    inside = -math.inf
    for axis in range(3):
        o = boxes[row, 6 + axis] * qx + boxes[row, 9 + axis] * qy + boxes[row, 12 + axis] * qz
        q = abs(o) - boxes[row, 3 + axis]
        if q > 0.0:
            outside2 += q * q
        inside = max(inside, q)
    return math.sqrt(outside2) + min(inside, 0.0)


@njit(cache=True)
def _sphere_sdf(spheres, row, x, y, z):
    qx = x - spheres[row, 0]
    qy = y - spheres[row, 1]
    qz = z - spheres[row, 2]
    return math.sqrt(qx * qx + qy * qy + qz * qz) - spheres[row, 3]


@njit(cache=True)
def _cylinder_sdf(cylinders, row, x, y, z):
    # A 2-D box in (distance from the axis, position along it).
    wx, wy, wz, length = _cylinder_axis(cylinders, row)
    qx = x - cylinders[row, 0]
    qy = y - cylinders[row, 1]
    qz = z - cylinders[row, 2]
    h = qx * wx + qy * wy + qz * wz
    px = qx - h * wx
    py = qy - h * wy
    pz = qz - h * wz
    radial = math.sqrt(px * px + py * py + pz * pz) - cylinders[row, 6]
    axial = abs(h - 0.5 * length) - 0.5 * length
    out_r = max(radial, 0.0)
    out_a = max(axial, 0.0)
    return min(max(radial, axial), 0.0) + math.sqrt(out_r * out_r + out_a * out_a)


# --- axis-aligned boxes and validation ---------------------------------------------------------


def _solid_boxes(
    boxes: np.ndarray, spheres: np.ndarray, cylinders: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Axis-aligned boxes ``(lo, hi)`` (n, 3) of all solids, with their kinds and rows."""
    R = boxes[:, 6:15].reshape(-1, 3, 3)
    box_half = np.einsum("nij,nj->ni", np.abs(R), boxes[:, 3:6])
    axis = cylinders[:, 3:6] - cylinders[:, 0:3]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    cyl_half = cylinders[:, 6:7] * np.sqrt(np.clip(1.0 - axis * axis, 0.0, 1.0))
    lo = np.concatenate(
        [
            boxes[:, 0:3] - box_half,
            spheres[:, 0:3] - spheres[:, 3:4],
            np.minimum(cylinders[:, 0:3], cylinders[:, 3:6]) - cyl_half,
        ]
    )
    hi = np.concatenate(
        [
            boxes[:, 0:3] + box_half,
            spheres[:, 0:3] + spheres[:, 3:4],
            np.maximum(cylinders[:, 0:3], cylinders[:, 3:6]) + cyl_half,
        ]
    )
    kind = np.concatenate(
        [
            np.full(len(boxes), _BOX, np.int64),
            np.full(len(spheres), _SPHERE, np.int64),
            np.full(len(cylinders), _CYLINDER, np.int64),
        ]
    )
    row = np.concatenate(
        [np.arange(len(boxes)), np.arange(len(spheres)), np.arange(len(cylinders))]
    ).astype(np.int64)
    return lo, hi, kind, row


def _solid_rows(value: Any, columns: int, name: str) -> np.ndarray:
    try:
        rows = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(name, "must be an array of numbers") from None
    if rows.size == 0:
        rows = rows.reshape(0, columns)
    if rows.ndim != 2 or rows.shape[1] != columns:
        raise InvalidInputError(name, f"must have shape (n, {columns}), got {rows.shape}")
    if not np.all(np.isfinite(rows)):
        raise InvalidInputError(name, "has non-finite entries (NaN or inf)")
    rows = np.ascontiguousarray(rows)
    rows.setflags(write=False)
    return rows


def _check_solids(boxes: np.ndarray, spheres: np.ndarray, cylinders: np.ndarray) -> None:
    if np.any(boxes[:, 3:6] <= 0.0):
        raise InvalidInputError("scene.boxes", "half extents must be > 0")
    R = boxes[:, 6:15].reshape(-1, 3, 3)
    if len(boxes):
        err = np.abs(np.einsum("nki,nkj->nij", R, R) - np.eye(3)).max(axis=(1, 2))
        bad = np.flatnonzero((err > _ROTATION_TOLERANCE) | (np.linalg.det(R) < 0.0))
        if bad.size:
            raise InvalidInputError(
                "scene.boxes", f"row {bad[0]}: the rotation (columns 6-14) is not a rotation matrix"
            )
    if np.any(spheres[:, 3] <= 0.0):
        raise InvalidInputError("scene.spheres", "radii must be > 0")
    if np.any(cylinders[:, 6] <= 0.0):
        raise InvalidInputError("scene.cylinders", "radii must be > 0")
    if np.any(np.linalg.norm(cylinders[:, 3:6] - cylinders[:, 0:3], axis=1) <= 0.0):
        raise InvalidInputError("scene.cylinders", "end points a and b must differ")
