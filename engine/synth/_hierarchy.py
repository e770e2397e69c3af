"""The bounding-volume hierarchy over a scene's solids: its build and the kernels that walk it.

The hierarchy is a median split of the solids' axis-aligned boxes, built once per scene, so
that the cost of a ray or a point grows with the logarithm of the number of solids.
:func:`_first_hit` walks it along a ray (the first entry into any solid), :func:`_nearest`
towards a point (the smallest signed distance); :func:`_cast_kernel` and
:func:`_distance_kernel` run them over many rays or points in parallel, and the render kernel
(:mod:`._render`) over the pixel rays of a sensor.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..errors import InvalidInputError
from ._solids import (
    _BOX,
    _SPHERE,
    _box_interval,
    _box_sdf,
    _cylinder_interval,
    _cylinder_sdf,
    _sphere_interval,
    _sphere_sdf,
)

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


# --- building the hierarchy --------------------------------------------------------------------


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
