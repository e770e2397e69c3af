"""Synthetic range data: analytic scenes rendered into range maps (FORMAT.md encoding).

An :class:`AnalyticScene` is a union of convex solids (oriented boxes, spheres and capped
cylinders) with exact ray casting and exact signed distances, so that tests and benchmarks
know the true surface of everything they fuse (STYLE.md 17). :func:`render` turns a scene,
a sensor and a pose ``T_W_S`` into the range map the sensor would measure (``+inf``: no
return within ``max_range``, NaN: closer than ``min_range``); :func:`apply_noise` adds
range noise, spikes, dropouts and an invalid background; :func:`make_dataset` builds the
three scenes of ``rangefuse synth`` (``object``, ``room``, ``street``) with their sensors
and poses.

Ray casting and distances run in numba kernels over a bounding-volume hierarchy (median
split of the solids' boxes, built once per scene), so that the cost of a ray grows with the
logarithm of the number of solids and a 1 km street renders as fast as a 40 m one.
Geometry and poses are deterministic; only the noise depends on the seed.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike

from . import _sensor_kernels as _k
from .errors import InvalidInputError
from .scans import Scan, check_pose
from .sensors import PinholeSensor, Sensor, SphericalSensor

__all__ = [
    "SCENES",
    "AnalyticScene",
    "NoiseSpec",
    "SceneBuilder",
    "SyntheticDataset",
    "apply_noise",
    "make_dataset",
    "parse_noise",
    "render",
]

SCENES: tuple[str, ...] = ("object", "room", "street")

# --- solids and the bounding-volume hierarchy --------------------------------------------------

_BOX_COLUMNS = 15  # centre(3), half extents(3), rotation box -> world, row-major (9)
_SPHERE_COLUMNS = 4  # centre(3), radius
_CYLINDER_COLUMNS = 7  # end point a(3), end point b(3), radius
_BOX = 0
_SPHERE = 1
_CYLINDER = 2
#: Largest deviation of ``R^T R`` from the identity accepted in a box rotation.
_ROTATION_TOLERANCE = 1e-6
#: Solids per leaf of the hierarchy.
_LEAF_SIZE = 4
#: Traversal stack of one ray; the median split keeps the depth near log2(solids / leaf).
_STACK_DEPTH = 64
#: Rays (or points) handled by one parallel task, which owns one traversal stack.
_ITEMS_PER_TASK = 256
#: Relative padding of node boxes against rounding at faces that touch them.
_NODE_PAD = 1e-9
#: Stand-in for 1/0 in slab tests (a direction component of exactly zero).
_HUGE = 1e300
#: Below this squared length of its off-axis part a ray runs parallel to a cylinder axis.
_PARALLEL_EPS = 1e-18


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


@njit(cache=True)
def _safe_inverse(d):
    if d == 0.0:
        return _HUGE
    return 1.0 / d


# The hierarchy reaches the kernels as three arrays (built by ``_build_hierarchy``):
# bounds float64 (n_nodes, 6): lo(3), hi(3) of each node's box;
# links int64 (n_nodes, 4): first solid and solid count of a leaf (count 0: inner node),
#     right child and split axis of an inner node (its left child is the next node);
# solids int64 (n_solids, 2): kind (_BOX, _SPHERE, _CYLINDER) and row, in leaf order.
_FIRST = 0
_COUNT = 1
_RIGHT = 2
_AXIS = 3


@njit(cache=True)
def _first_hit(boxes, spheres, cylinders, bounds, links, solids, ray, t_max, stack):
    """Smallest entry ``t`` in ``[0, t_max]`` of ray ``(ox, oy, oz, dx, dy, dz)``, or inf."""
    ox, oy, oz, dx, dy, dz = ray
    best = math.inf
    if bounds.shape[0] == 0:
        return best
    ix = _safe_inverse(dx)
    iy = _safe_inverse(dy)
    iz = _safe_inverse(dz)
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        t1 = (bounds[node, 0] - ox) * ix
        t2 = (bounds[node, 3] - ox) * ix
        t_near = min(t1, t2)
        t_far = max(t1, t2)
        t1 = (bounds[node, 1] - oy) * iy
        t2 = (bounds[node, 4] - oy) * iy
        t_near = max(t_near, min(t1, t2))
        t_far = min(t_far, max(t1, t2))
        t1 = (bounds[node, 2] - oz) * iz
        t2 = (bounds[node, 5] - oz) * iz
        t_near = max(t_near, min(t1, t2))
        t_far = min(t_far, max(t1, t2))
        if t_near > t_far or t_far < 0.0 or t_near > t_max or t_near >= best:
            continue
        count = links[node, _COUNT]
        if count > 0:
            first = links[node, _FIRST]
            for k in range(first, first + count):
                kind = solids[k, 0]
                row = solids[k, 1]
                if kind == _BOX:
                    t_in, t_out = _box_interval(boxes, row, ox, oy, oz, dx, dy, dz)
                elif kind == _SPHERE:
                    t_in, t_out = _sphere_interval(spheres, row, ox, oy, oz, dx, dy, dz)
                else:
                    t_in, t_out = _cylinder_interval(cylinders, row, ox, oy, oz, dx, dy, dz)
                if t_in <= t_out and t_out > 0.0:
                    t = max(t_in, 0.0)  # a ray that starts inside hits at 0
                    if t < best and t <= t_max:
                        best = t
        else:
            near = node + 1
            far = links[node, _RIGHT]
            axis = links[node, _AXIS]
            if (dx if axis == 0 else (dy if axis == 1 else dz)) < 0.0:
                near, far = far, near
            stack[top] = far  # visit the nearer child first
            stack[top + 1] = near
            top += 2
    return best


@njit(cache=True, parallel=True)
def _cast_kernel(boxes, spheres, cylinders, bounds, links, solids, origins, directions, t_max, out):
    """First hit ``out[i]`` (inf on a miss or beyond ``t_max[i]``) of ray ``i``."""
    n_rays = origins.shape[0]
    n_tasks = (n_rays + _ITEMS_PER_TASK - 1) // _ITEMS_PER_TASK
    for task in prange(n_tasks):
        stack = np.empty(_STACK_DEPTH, np.int64)
        stop = min(n_rays, (task + 1) * _ITEMS_PER_TASK)
        for i in range(task * _ITEMS_PER_TASK, stop):
            ray = (
                origins[i, 0], origins[i, 1], origins[i, 2],
                directions[i, 0], directions[i, 1], directions[i, 2],
            )  # fmt: skip
            out[i] = _first_hit(
                boxes, spheres, cylinders, bounds, links, solids, ray, t_max[i], stack
            )


@njit(cache=True, parallel=True)
def _render_kernel(
    boxes, spheres, cylinders, bounds, links, solids, T_W_S, origins_S, directions_S, t_max,
    kind, params, table, out,
):  # fmt: skip
    """Range ``out[i]`` of pixel ray ``i`` (sensor frame): the hit point's distance in the
    sensor's convention, inf on a miss or beyond ``max_range``, NaN closer than ``min_range``."""
    min_range = params[_k.P_MIN_RANGE]
    max_range = params[_k.P_MAX_RANGE]
    T = T_W_S
    n_rays = origins_S.shape[0]
    n_tasks = (n_rays + _ITEMS_PER_TASK - 1) // _ITEMS_PER_TASK
    for task in prange(n_tasks):
        stack = np.empty(_STACK_DEPTH, np.int64)
        stop = min(n_rays, (task + 1) * _ITEMS_PER_TASK)
        for i in range(task * _ITEMS_PER_TASK, stop):
            sx, sy, sz = origins_S[i, 0], origins_S[i, 1], origins_S[i, 2]
            ex, ey, ez = directions_S[i, 0], directions_S[i, 1], directions_S[i, 2]
            ray_W = (
                T[0, 0] * sx + T[0, 1] * sy + T[0, 2] * sz + T[0, 3],
                T[1, 0] * sx + T[1, 1] * sy + T[1, 2] * sz + T[1, 3],
                T[2, 0] * sx + T[2, 1] * sy + T[2, 2] * sz + T[2, 3],
                T[0, 0] * ex + T[0, 1] * ey + T[0, 2] * ez,
                T[1, 0] * ex + T[1, 1] * ey + T[1, 2] * ez,
                T[2, 0] * ex + T[2, 1] * ey + T[2, 2] * ez,
            )
            t = _first_hit(boxes, spheres, cylinders, bounds, links, solids, ray_W, t_max[i], stack)
            if t == math.inf:
                out[i] = math.inf
                continue
            # The hit point in the sensor frame, straight from the sensor-frame ray.
            d = _k.project_point(kind, params, table, sx + t * ex, sy + t * ey, sz + t * ez)[2]
            if d > max_range:
                out[i] = math.inf
            elif d < min_range or math.isnan(d):
                out[i] = math.nan
            else:
                out[i] = d


@njit(cache=True)
def _gap(bounds, node, x, y, z):
    # Distance from a point to a node's box (0 inside).
    gx = max(bounds[node, 0] - x, x - bounds[node, 3], 0.0)
    gy = max(bounds[node, 1] - y, y - bounds[node, 4], 0.0)
    gz = max(bounds[node, 2] - z, z - bounds[node, 5], 0.0)
    return math.sqrt(gx * gx + gy * gy + gz * gz)


@njit(cache=True)
def _nearest(boxes, spheres, cylinders, bounds, links, solids, x, y, z, stack):
    # min over solids of their signed distance; a node whose box is farther than the best
    # distance so far cannot hold a smaller one (a solid's distance >= its box's distance).
    best = math.inf
    if bounds.shape[0] == 0:
        return best
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        gap = _gap(bounds, node, x, y, z)
        if gap > 0.0 and gap >= best:
            continue
        count = links[node, _COUNT]
        if count > 0:
            first = links[node, _FIRST]
            for k in range(first, first + count):
                kind = solids[k, 0]
                row = solids[k, 1]
                if kind == _BOX:
                    s = _box_sdf(boxes, row, x, y, z)
                elif kind == _SPHERE:
                    s = _sphere_sdf(spheres, row, x, y, z)
                else:
                    s = _cylinder_sdf(cylinders, row, x, y, z)
                best = min(best, s)
        else:
            near = node + 1
            far = links[node, _RIGHT]
            if _gap(bounds, far, x, y, z) < _gap(bounds, near, x, y, z):
                near, far = far, near
            stack[top] = far
            stack[top + 1] = near
            top += 2
    return best


@njit(cache=True, parallel=True)
def _distance_kernel(boxes, spheres, cylinders, bounds, links, solids, points, out):
    """Signed distance ``out[i]`` of point ``i`` to the union of solids."""
    n_points = points.shape[0]
    n_tasks = (n_points + _ITEMS_PER_TASK - 1) // _ITEMS_PER_TASK
    for task in prange(n_tasks):
        stack = np.empty(_STACK_DEPTH, np.int64)
        stop = min(n_points, (task + 1) * _ITEMS_PER_TASK)
        for i in range(task * _ITEMS_PER_TASK, stop):
            out[i] = _nearest(
                boxes, spheres, cylinders, bounds, links, solids,
                points[i, 0], points[i, 1], points[i, 2], stack,
            )  # fmt: skip


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


def _build_hierarchy(
    lo: np.ndarray, hi: np.ndarray, kind: np.ndarray, row: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bounding-volume hierarchy ``(bounds, links, solids)`` (layout above ``_first_hit``):
    median split along the longest extent of the solids' centres, nodes depth first."""
    n = lo.shape[0]
    pad = _NODE_PAD * (1.0 + np.maximum(np.abs(lo), np.abs(hi)))
    lo = lo - pad
    hi = hi + pad
    centre = 0.5 * (lo + hi)
    order = np.arange(n)
    n_max = max(2 * n - 1, 0)
    bounds = np.zeros((n_max, 6))
    links = np.zeros((n_max, 4), np.int64)
    n_nodes = 0
    max_depth = 0

    def build(start: int, stop: int, depth: int) -> int:
        nonlocal n_nodes, max_depth
        node = n_nodes
        n_nodes += 1
        max_depth = max(max_depth, depth)
        members = order[start:stop]
        bounds[node, :3] = lo[members].min(axis=0)
        bounds[node, 3:] = hi[members].max(axis=0)
        if stop - start <= _LEAF_SIZE:
            links[node, _FIRST] = start
            links[node, _COUNT] = stop - start
            return node
        c = centre[members]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        mid = (start + stop) // 2
        order[start:stop] = members[np.argpartition(c[:, axis], mid - start)]
        links[node, _AXIS] = axis
        build(start, mid, depth + 1)
        links[node, _RIGHT] = build(mid, stop, depth + 1)
        return node

    if n:
        build(0, n, 0)
    if max_depth + 2 > _STACK_DEPTH:  # pragma: no cover - needs ~2**60 solids
        raise InvalidInputError("scene", f"too many solids ({n}) for the ray-casting stack")
    solids = np.ascontiguousarray(np.column_stack([kind[order], row[order]]), np.int64)
    return bounds[:n_nodes].copy(), links[:n_nodes].copy(), solids


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


def _points(value: Any, name: str) -> np.ndarray:
    try:
        points = np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(name, "must be an (n, 3) array of numbers") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(name, f"must have shape (n, 3), got {points.shape}")
    return points


#: ``(boxes, spheres, cylinders, bounds, links, solids)``: a scene as the kernels take it.
_KernelScene = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _empty_rows(columns: int) -> Callable[[], np.ndarray]:
    return lambda: np.zeros((0, columns))


@dataclass(frozen=True, eq=False)
class AnalyticScene:
    """A union of convex solids: oriented boxes, spheres, capped cylinders.

    Parameters
    ----------
    boxes : array (nb, 15)
        Centre (3), half extents (3, metres, > 0), rotation matrix box -> world, row-major (9):
        ``x_W = centre + R x_B``.
    spheres : array (ns, 4)
        Centre (3), radius (metres, > 0).
    cylinders : array (nc, 7)
        End point ``a`` (3), end point ``b`` (3), radius (metres, > 0); flat caps at both ends.

    All arrays are stored as read-only float64. Invalid solids raise
    :class:`~engine.errors.InvalidInputError` naming the array.
    """

    boxes: np.ndarray = field(default_factory=_empty_rows(_BOX_COLUMNS))
    spheres: np.ndarray = field(default_factory=_empty_rows(_SPHERE_COLUMNS))
    cylinders: np.ndarray = field(default_factory=_empty_rows(_CYLINDER_COLUMNS))
    # Derived in __post_init__: the solids' axis-aligned boxes and the kernels' arguments.
    _lo: np.ndarray = field(init=False, repr=False)
    _hi: np.ndarray = field(init=False, repr=False)
    _kernel_args: _KernelScene = field(init=False, repr=False)

    def __post_init__(self) -> None:
        boxes = _solid_rows(self.boxes, _BOX_COLUMNS, "scene.boxes")
        spheres = _solid_rows(self.spheres, _SPHERE_COLUMNS, "scene.spheres")
        cylinders = _solid_rows(self.cylinders, _CYLINDER_COLUMNS, "scene.cylinders")
        _check_solids(boxes, spheres, cylinders)
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "spheres", spheres)
        object.__setattr__(self, "cylinders", cylinders)
        lo, hi, kind, row = _solid_boxes(boxes, spheres, cylinders)
        object.__setattr__(self, "_lo", lo)
        object.__setattr__(self, "_hi", hi)
        tree = _build_hierarchy(lo, hi, kind, row)
        object.__setattr__(self, "_kernel_args", (boxes, spheres, cylinders, *tree))

    @property
    def n_solids(self) -> int:
        """Number of solids (boxes, spheres and cylinders together)."""
        return len(self.boxes) + len(self.spheres) + len(self.cylinders)

    def _cast(
        self, origins_W: np.ndarray, directions_W: np.ndarray, t_max: np.ndarray
    ) -> np.ndarray:
        out = np.empty(origins_W.shape[0], np.float64)
        _cast_kernel(*self._kernel_args, origins_W, directions_W, t_max, out)
        return out

    def cast(self, origins_W: np.ndarray, directions_W: np.ndarray) -> np.ndarray:
        """Distance along each ray to the first surface.

        Parameters
        ----------
        origins_W : array (n, 3)
            Ray origins, world frame, metres.
        directions_W : array (n, 3)
            Unit ray directions, world frame (with other lengths ``t`` is in their units).

        Returns
        -------
        t : float64 array (n,)
            Smallest ``t >= 0`` at which ``origin + t direction`` enters a solid whose exit lies
            ahead (``t = 0`` for a ray that starts inside a solid); ``+inf`` on a miss.
        """
        origins = _points(origins_W, "origins_W")
        directions = _points(directions_W, "directions_W")
        if origins.shape != directions.shape:
            raise InvalidInputError(
                "directions_W", f"shape {directions.shape} differs from origins {origins.shape}"
            )
        return self._cast(origins, directions, np.full(origins.shape[0], math.inf))

    def signed_distance(self, points_W: np.ndarray) -> np.ndarray:
        """Signed distance of points to the scene, metres (negative inside a solid).

        Parameters
        ----------
        points_W : array (n, 3)
            World points, metres.

        Returns
        -------
        float64 array (n,)
            The minimum over solids of each solid's exact signed distance: exact outside the
            union; inside, minus the depth within the solid that holds the point deepest.
            ``+inf`` for an empty scene.
        """
        points = _points(points_W, "points_W")
        out = np.empty(points.shape[0], np.float64)
        _distance_kernel(*self._kernel_args, points, out)
        return out

    def bounds(self) -> tuple[float, float, float, float, float, float]:
        """Axis-aligned bounds ``(x0, y0, z0, x1, y1, z1)`` of all solids, metres."""
        if self.n_solids == 0:
            raise InvalidInputError("scene", "is empty: it has no bounds")
        lo = self._lo.min(axis=0)
        hi = self._hi.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: ``{"boxes": [[15 numbers], ...], "spheres": ..., "cylinders": ...}``."""
        return {
            "boxes": self.boxes.tolist(),
            "spheres": self.spheres.tolist(),
            "cylinders": self.cylinders.tolist(),
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> AnalyticScene:
        """Inverse of :meth:`to_dict`; a missing list means no solids of that kind."""
        if not isinstance(data, dict):
            raise InvalidInputError("scene", f"must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - {"boxes", "spheres", "cylinders"})
        if unknown:
            raise InvalidInputError(f"scene.{unknown[0]}", "unknown field")
        return AnalyticScene(
            boxes=data.get("boxes", np.zeros((0, _BOX_COLUMNS))),
            spheres=data.get("spheres", np.zeros((0, _SPHERE_COLUMNS))),
            cylinders=data.get("cylinders", np.zeros((0, _CYLINDER_COLUMNS))),
        )


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


# --- rendering ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=4)
def _sensor_rays(sensor: Sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel rays ``(origins_S, directions_S)`` (H*W, 3) and the ray length ``t_max`` (H*W,)
    beyond which the range exceeds ``max_range``.

    Every model's range grows linearly along its pixel rays, so two points fix the rate; where
    that fails ``t_max`` is inf (render still tests the range of every hit).
    """
    origins, directions = sensor.pixel_rays()
    origins = np.ascontiguousarray(origins.reshape(-1, 3))
    directions = np.ascontiguousarray(directions.reshape(-1, 3))
    d1 = sensor.project(origins + directions)[2]
    d2 = sensor.project(origins + 2.0 * directions)[2]
    rate = d2 - d1
    with np.errstate(invalid="ignore", divide="ignore"):
        t_max = 1.0 + (sensor.max_range - d1) / rate
    t_max = np.where(np.isfinite(t_max) & (rate > 0.0), t_max * (1.0 + 1e-6) + 1e-6, math.inf)
    for array in (origins, directions, t_max):
        array.setflags(write=False)
    return origins, directions, t_max


def render(scene: AnalyticScene, sensor: Sensor, T_W_S: np.ndarray) -> np.ndarray:
    """Range map of a scene seen by a sensor (FORMAT.md encoding).

    Parameters
    ----------
    scene : AnalyticScene
    sensor : Sensor
        Any sensor model; its pixel rays (:meth:`Sensor.pixel_rays`) are cast into the scene.
    T_W_S : array (4, 4)
        Sensor-to-world pose, rigid.

    Returns
    -------
    float32 array (H, W)
        Distance of the first hit in the sensor's range convention (``sensor.project`` of the
        hit point, e.g. z-depth for a ``"z"`` pinhole camera); ``+inf`` for a miss or a hit
        beyond ``max_range`` (no return), NaN for a hit closer than ``min_range`` (invalid).
    """
    if not isinstance(scene, AnalyticScene):
        raise InvalidInputError("scene", f"must be an AnalyticScene, got {type(scene).__name__}")
    if not isinstance(sensor, Sensor):
        raise InvalidInputError("sensor", f"must be a Sensor, got {type(sensor).__name__}")
    T = check_pose(T_W_S, "T_W_S")
    origins_S, directions_S, t_max = _sensor_rays(sensor)
    kind, params, table = sensor.kernel_args()
    out = np.empty(origins_S.shape[0], np.float32)
    _render_kernel(*scene._kernel_args, T, origins_S, directions_S, t_max, kind, params, table, out)
    return out.reshape(sensor.shape)


# --- noise -------------------------------------------------------------------------------------

_NOISE_KINDS = ("uniform", "gaussian", "spikes", "dropouts", "background")
_NOISE_FIELDS = {
    "uniform": "uniform_m",
    "gaussian": "gaussian_m",
    "spikes": "spikes",
    "dropouts": "dropouts",
    "background": "background",
}
_NOISE_GRAMMAR = (
    "valid kinds: uniform:<metres>, gaussian:<metres>, spikes:<fraction>, dropouts:<fraction>, "
    "background:inf|nan, or 'none'"
)
_BACKGROUNDS = ("inf", "nan")
#: Noisy ranges are clipped to at least max(min_range, this), so that they stay positive.
_MIN_NOISY_RANGE_M = 1e-3


@dataclass(frozen=True)
class NoiseSpec:
    """Measurement noise added to rendered range maps (see :func:`apply_noise`).

    Parameters
    ----------
    uniform_m : float
        Half-width of additive uniform noise, metres (>= 0).
    gaussian_m : float
        Standard deviation of additive Gaussian noise, metres (>= 0).
    spikes : float
        Fraction of valid (finite) pixels replaced by a uniform random range in
        ``[min_range, max_range]`` (outliers), in [0, 1].
    dropouts : float
        Fraction of all pixels set to NaN (invalid), in [0, 1].
    background : {"inf", "nan"}
        How misses are written: ``"inf"`` (no return) or ``"nan"`` (invalid).
    """

    uniform_m: float = 0.0
    gaussian_m: float = 0.0
    spikes: float = 0.0
    dropouts: float = 0.0
    background: str = "inf"

    def __post_init__(self) -> None:
        for name in ("uniform_m", "gaussian_m", "spikes", "dropouts"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise InvalidInputError(f"noise.{name}", f"must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value) or value < 0.0:
                raise InvalidInputError(f"noise.{name}", f"must be finite and >= 0, got {value}")
            if name in ("spikes", "dropouts") and value > 1.0:
                raise InvalidInputError(f"noise.{name}", f"is a fraction in [0, 1], got {value}")
            object.__setattr__(self, name, value)
        if self.background not in _BACKGROUNDS:
            raise InvalidInputError(
                "noise.background", f"must be 'inf' or 'nan', got {self.background!r}"
            )

    def to_spec(self) -> str:
        """The :func:`parse_noise` form of this noise (``"none"`` when it adds nothing)."""
        items = [
            f"{kind}:{getattr(self, _NOISE_FIELDS[kind]):g}"
            for kind in _NOISE_KINDS[:4]
            if getattr(self, _NOISE_FIELDS[kind]) > 0.0
        ]
        if self.background != "inf":
            items.append(f"background:{self.background}")
        return ",".join(items) if items else "none"

    def to_dict(self) -> dict[str, Any]:
        return {
            "uniform_m": self.uniform_m,
            "gaussian_m": self.gaussian_m,
            "spikes": self.spikes,
            "dropouts": self.dropouts,
            "background": self.background,
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> NoiseSpec:
        if not isinstance(data, dict):
            raise InvalidInputError("noise", f"must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_NOISE_FIELDS.values()))
        if unknown:
            raise InvalidInputError(f"noise.{unknown[0]}", "unknown field")
        return NoiseSpec(**data)


def _noise_error(item: str, problem: str) -> InvalidInputError:
    return InvalidInputError("noise", f"item {item!r}: {problem} ({_NOISE_GRAMMAR})")


def parse_noise(spec: str) -> NoiseSpec:
    """Parse a noise specification such as ``"gaussian:0.005,dropouts:0.05"``.

    Parameters
    ----------
    spec : str
        ``"none"`` (or empty), or comma-separated ``kind:value`` items: ``uniform:M`` and
        ``gaussian:M`` (metres, >= 0), ``spikes:F`` and ``dropouts:F`` (fractions in [0, 1]),
        ``background:inf`` or ``background:nan``. Each kind at most once.

    Returns
    -------
    NoiseSpec

    Raises
    ------
    InvalidInputError
        Field ``"noise"``; the message names the offending item and lists the valid kinds.
    """
    if not isinstance(spec, str):
        raise InvalidInputError("noise", f"must be a string, got {type(spec).__name__}")
    text = spec.strip()
    if text.lower() in ("", "none"):
        return NoiseSpec()
    values: dict[str, Any] = {}
    for raw in text.split(","):
        item = raw.strip()
        if not item:
            raise _noise_error(raw, "empty item")
        kind, sep, value_text = item.partition(":")
        kind = kind.strip().lower()
        value_text = value_text.strip()
        if kind not in _NOISE_KINDS:
            raise _noise_error(item, f"unknown kind {kind!r}")
        if not sep or not value_text:
            raise _noise_error(item, f"{kind} needs a value after ':'")
        if _NOISE_FIELDS[kind] in values:
            raise _noise_error(item, f"{kind} is given twice")
        if kind == "background":
            if value_text.lower() not in _BACKGROUNDS:
                raise _noise_error(item, f"background must be inf or nan, got {value_text!r}")
            values["background"] = value_text.lower()
            continue
        try:
            value = float(value_text)
        except ValueError:
            raise _noise_error(item, f"{value_text!r} is not a number") from None
        if not math.isfinite(value):
            raise _noise_error(item, f"{value_text!r} is not a finite number")
        if value < 0.0:
            raise _noise_error(item, f"{kind} must be >= 0, got {value:g}")
        if kind in ("spikes", "dropouts") and value > 1.0:
            raise _noise_error(item, f"{kind} is a fraction in [0, 1], got {value:g}")
        values[_NOISE_FIELDS[kind]] = value
    return NoiseSpec(**values)


def apply_noise(
    range_m: np.ndarray, noise: NoiseSpec, sensor: Sensor, rng: np.random.Generator
) -> np.ndarray:
    """Noisy copy of a range map.

    Parameters
    ----------
    range_m : array (H, W)
        Range map in the FORMAT.md encoding (finite, ``+inf`` no return, NaN invalid).
    noise : NoiseSpec
    sensor : Sensor
        Gives ``min_range`` and ``max_range``; ``sensor.shape`` must match the map.
    rng : numpy.random.Generator
        Source of all randomness (same state, same result).

    Returns
    -------
    float32 array (H, W)
        Uniform and Gaussian noise are added to the finite pixels, which then stay at least
        ``max(min_range, 1 mm)``; a ``spikes`` fraction of the finite pixels is replaced by a
        range drawn uniformly in that floor .. ``max_range``; a ``dropouts`` fraction of all
        pixels becomes NaN; with ``background="nan"`` every ``+inf`` becomes NaN.
    """
    if not isinstance(noise, NoiseSpec):
        raise InvalidInputError("noise", f"must be a NoiseSpec, got {type(noise).__name__}")
    values = np.array(range_m, dtype=np.float64)
    if values.shape != sensor.shape:
        raise InvalidInputError(
            "range", f"shape {values.shape} does not match the sensor's {sensor.shape}"
        )
    floor_m = max(sensor.min_range, _MIN_NOISY_RANGE_M)
    hit = np.flatnonzero(np.isfinite(values))
    flat = values.reshape(-1)
    measured = flat[hit]
    if noise.uniform_m > 0.0:
        measured += rng.uniform(-noise.uniform_m, noise.uniform_m, hit.size)
    if noise.gaussian_m > 0.0:
        measured += rng.normal(0.0, noise.gaussian_m, hit.size)
    np.maximum(measured, floor_m, out=measured)
    if noise.spikes > 0.0:
        spike = rng.random(hit.size) < noise.spikes
        measured[spike] = rng.uniform(floor_m, max(sensor.max_range, floor_m), int(spike.sum()))
    flat[hit] = measured
    if noise.dropouts > 0.0:
        flat[rng.random(flat.size) < noise.dropouts] = math.nan
    if noise.background == "nan":
        flat[np.isposinf(flat)] = math.nan
    return flat.reshape(sensor.shape).astype(np.float32)


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


# --- datasets ----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SyntheticDataset:
    """A rendered scene: the solids, the sensor and the scans (see :func:`make_dataset`).

    Parameters
    ----------
    name : str
        One of :data:`SCENES`.
    scene : AnalyticScene
        The true geometry.
    sensor : Sensor
        The sensor of every scan.
    scans : list of (str, Scan)
        ``("scan_0000", Scan), ...`` in order.
    bounds_m : (x0, y0, z0, x1, y1, z1)
        Region of interest for closed-mode fusion: the scene's solids plus a small margin.
    """

    name: str
    scene: AnalyticScene
    sensor: Sensor
    scans: list[tuple[str, Scan]]
    bounds_m: tuple[float, float, float, float, float, float]


def _check_views(views: Any) -> int | None:
    if views is None:
        return None
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)):
        raise InvalidInputError("views", f"must be an integer, got {views!r}")
    if views < 1:
        raise InvalidInputError("views", f"must be at least 1, got {views}")
    return int(views)


def _check_length(name: str, length_m: Any) -> float:
    if length_m is None:
        return _STREET_LENGTH_M
    if name != "street":
        raise InvalidInputError("length_m", f"applies to the street scene only, not {name!r}")
    if isinstance(length_m, bool) or not isinstance(length_m, (int, float, np.number)):
        raise InvalidInputError("length_m", f"must be a number of metres, got {length_m!r}")
    value = float(length_m)
    if not (math.isfinite(value) and 0.0 < value <= _STREET_MAX_LENGTH_M):
        raise InvalidInputError(
            "length_m", f"must be > 0 and at most {_STREET_MAX_LENGTH_M:g} m, got {length_m!r}"
        )
    return value


def make_dataset(
    name: str,
    views: int | None = None,
    noise: NoiseSpec | None = None,
    seed: int = 0,
    length_m: float | None = None,
) -> SyntheticDataset:
    """Render one of the synthetic scenes.

    Parameters
    ----------
    name : {"object", "room", "street"}
        ``object``: a robot arm about 0.9 m across seen by a 640x480 ray-range pinhole camera
        from ``views`` (default 12) directions on a 2 m sphere; ``room``: a furnished
        5 x 4 x 2.6 m room seen by a 640x480 z-depth RGB-D camera on a closed loop (default 100
        views); ``street``: a street seen by a 64-beam spherical LiDAR 1.8 m above the road,
        one scan every 2 m by default.
    views : int or None
        Number of scans (>= 1); None for the scene's default.
    noise : NoiseSpec or None
        Noise added to every scan (see :func:`apply_noise`); None for none.
    seed : int
        Seed of the noise (``np.random.default_rng(seed)``); geometry and poses do not depend
        on it.
    length_m : float or None
        Street length in metres (default 40); street only.

    Returns
    -------
    SyntheticDataset

    Raises
    ------
    InvalidInputError
        Naming ``name``, ``views``, ``noise`` or ``length_m``.
    """
    if name not in SCENES:
        raise InvalidInputError(
            "name", f"unknown scene {name!r}; expected one of {', '.join(SCENES)}"
        )
    n_views = _check_views(views)
    length = _check_length(name, length_m)
    if noise is None:
        noise = NoiseSpec()
    if not isinstance(noise, NoiseSpec):
        raise InvalidInputError("noise", f"must be a NoiseSpec, got {type(noise).__name__}")
    sensor: Sensor
    if name == "object":
        scene = _object_scene()
        sensor = _OBJECT_CAMERA
        poses = _object_poses(n_views or _OBJECT_VIEWS, scene)
        margin = _OBJECT_BOUNDS_MARGIN_M
    elif name == "room":
        scene = _room_scene()
        sensor = _ROOM_CAMERA
        poses = _room_poses(n_views or _ROOM_VIEWS)
        margin = _ROOM_BOUNDS_MARGIN_M
    else:
        scene = _street_scene(length)
        sensor = _STREET_LIDAR
        default = max(1, round(length / _STREET_SCAN_SPACING_M))
        poses = _street_poses(n_views or default, length)
        margin = _STREET_BOUNDS_MARGIN_M
    rng = np.random.default_rng(seed)
    scans = []
    for k, T_W_S in enumerate(poses):
        range_m = render(scene, sensor, T_W_S)
        if noise != NoiseSpec():
            range_m = apply_noise(range_m, noise, sensor, rng)
        scans.append((f"scan_{k:04d}", Scan(range_m=range_m, T_W_S=T_W_S, sensor=sensor)))
    x0, y0, z0, x1, y1, z1 = scene.bounds()
    bounds = (x0 - margin, y0 - margin, z0 - margin, x1 + margin, y1 + margin, z1 + margin)
    return SyntheticDataset(name=name, scene=scene, sensor=sensor, scans=scans, bounds_m=bounds)
