"""Analytic scenes and exact ray casting: convex solids, their hierarchy and the kernels.

An :class:`AnalyticScene` is a union of convex solids (oriented boxes, spheres and capped
cylinders) with exact ray casting and exact signed distances, so that tests and benchmarks
know the true surface of everything they fuse (STYLE.md 17). The class validates the solids
and is the API over the numba kernels of this module: per-solid ray intervals and signed
distances, and a bounding-volume hierarchy (median split of the solids' boxes, built once per
scene) whose traversal makes the cost of a ray grow with the logarithm of the number of
solids. The render kernel used by :func:`engine.synth.render` lives here too; the public
names are re-exported by :mod:`engine.synth`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from .errors import InvalidInputError

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


# --- the scene: validated solids, the API over the kernels -------------------------------------


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
