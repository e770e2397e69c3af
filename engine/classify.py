"""How a scan sees a tile (DESIGN.md invariants 1, 3, 4): out of view, free throughout, or
partly informed; and how far a scan reaches.

:func:`classify_tiles` says how the scan sees given tiles: ``OUT`` (it informs none of
their voxels), ``FREE`` (it informs every voxel, all in free space in front of the surface
band: the same contribution ``logit(rho)`` for each) or ``PARTIAL`` (the fusion kernel
decides voxel by voxel). The test is conservative: the tile's box of voxel centres is
bounded by a pixel rectangle (exact corner projection for pinhole and orthographic sensors,
the circumscribed sphere for spherical and cylindrical ones) and compared with block
statistics of the pixel quads under it (farthest informed distance, free-space bound;
:func:`engine._sampling.bounds_and_pyramid`). A pinhole box with all corners outside one
side of the image's pyramid is ``OUT`` too: a box across the sensor's plane ``z = 0`` has
no bounded rectangle. A tile is *in view* unless it is ``OUT``.

:func:`reach_radius` and :func:`bounding_sphere` bound a scan by a sphere around its sensor
outside which it informs nothing (the planner's test for the scans near new tiles).

The classification is a function of the scan alone, so the volume does not depend on the
order in which scans arrive. Tile keys are int64 (n, 3).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from ._sampling import PYRAMID_SPAN, QUAD_BLOCK, quad_columns, widened
from .certainty import SHAPE_LINEAR
from .grid import GridSpec
from .scans import FusionParams, PreparedScan, Scan

__all__ = [
    "FREE",
    "OUT",
    "PARTIAL",
    "bounding_sphere",
    "classify_tiles",
    "reach_radius",
    "tiles_in_view",
]

OUT = 0
PARTIAL = 1
FREE = 2

#: Slack, in pixels and metres, added to the conservative tests against rounding.
_PIXEL_SLACK = 1e-3
_DIST_SLACK = 1e-9
#: The most quads a part's test (:func:`_classify_part`) folds one by one; a larger pixel
#: rectangle reads the pyramid's blocks (a superset of its quads).
_EXACT_QUADS = 1024
#: No per-quad bounds: :func:`_rect_stats` reads the pyramid's blocks only.
_NO_BOUNDS = np.zeros(0, np.float32)
#: A part nearer than this (metres) to a spherical sensor's axis is tested on every column.
_AXIS_CLEARANCE = 1e-6


@njit(cache=True, inline="always")
def _clip_quads(lo, hi, n):
    """Quad index range covering continuous pixel interval [lo, hi], clipped to [0, n-1]."""
    if hi < 0.0 or lo > n:  # lo > n: past the last pixel even when it is the wrap quad
        return 0, -1
    a = int(math.floor(max(lo, 0.0)))
    b = int(math.floor(min(hi, float(n))))
    if a > n - 1:
        return 0, -1
    if b > n - 1:
        b = n - 1
    return a, b


@njit(cache=True, inline="always")
def _fold(acc, far, free):
    acc[0] = max(acc[0], far)
    acc[1] = min(acc[1], free)


@njit(cache=True)
def _blocks(reach, free, levels, qu0, qu1, qv0, qv1, acc):
    """Fold the block statistics over quads [qu0, qu1] x [qv0, qv1] into ``acc`` (largest
    reach, smallest free-space bound), from the finest pyramid level at which they cover
    fewer than ``PYRAMID_SPAN`` nodes per side."""
    bu0 = qu0 // QUAD_BLOCK
    bu1 = qu1 // QUAD_BLOCK
    bv0 = qv0 // QUAD_BLOCK
    bv1 = qv1 // QUAD_BLOCK
    level = 0
    while (bu1 - bu0 >= PYRAMID_SPAN or bv1 - bv0 >= PYRAMID_SPAN) and level + 1 < len(levels):
        bu0 >>= 1
        bu1 >>= 1
        bv0 >>= 1
        bv1 >>= 1
        level += 1
    offset = levels[level, 0]
    cols = levels[level, 2]
    for bv in range(bv0, bv1 + 1):
        for bu in range(bu0, bu1 + 1):
            _fold(acc, reach[offset + bv * cols + bu], free[offset + bv * cols + bu])


@njit(cache=True, inline="always")
def _quads(bounds, reach, free, levels, qu0, qu1, qv0, qv1, nqu, acc):
    """Fold the statistics of quads [qu0, qu1] x [qv0, qv1] into ``acc``: quad by quad from
    ``bounds`` (the flat float32 pairs of :func:`engine._sampling.quad_bounds`) when it is
    given and the rectangle has at most ``_EXACT_QUADS`` quads, else by :func:`_blocks`."""
    if bounds.shape[0] == 0 or (qu1 - qu0 + 1) * (qv1 - qv0 + 1) > _EXACT_QUADS:
        _blocks(reach, free, levels, qu0, qu1, qv0, qv1, acc)
        return
    for qv in range(qv0, qv1 + 1):
        row = 2 * qv * nqu
        for qu in range(qu0, qu1 + 1):
            _fold(acc, bounds[row + 2 * qu + 1], bounds[row + 2 * qu])


@njit(cache=True, inline="always")
def _rect_stats(bounds, reach, free, levels, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
    """Statistics of the quads under a pixel rectangle, into ``acc`` (see :func:`_quads`;
    an empty ``bounds`` reads the blocks of the pyramid only).

    ``ring > 0`` means columns are azimuth-periodic with that many columns per full turn;
    ``u_lo`` is then in ``[0, ring)`` and ``u_hi`` may exceed ``ring`` (the interval wraps).
    Returns False when the rectangle covers no quad.
    """
    acc[0] = -np.inf
    acc[1] = np.inf
    qv0, qv1 = _clip_quads(v_lo - _PIXEL_SLACK, v_hi + _PIXEL_SLACK, nqv)
    if qv1 < qv0:
        return False
    lo = u_lo - _PIXEL_SLACK
    hi = u_hi + _PIXEL_SLACK
    if ring > 0.0 and lo < 0.0:
        lo += ring
        hi += ring
    any_quad = False
    qu0, qu1 = _clip_quads(lo, hi, nqu)
    if qu1 >= qu0:
        _quads(bounds, reach, free, levels, qu0, qu1, qv0, qv1, nqu, acc)
        any_quad = True
    if ring > 0.0 and hi >= ring:
        qu0, qu1 = _clip_quads(0.0, hi - ring, nqu)
        if qu1 >= qu0:
            _quads(bounds, reach, free, levels, qu0, qu1, qv0, qv1, nqu, acc)
            any_quad = True
    return any_quad


@njit(cache=True, inline="always")
def _box_distance(lo, hi, p):
    s = 0.0
    for a in range(3):
        if p[a] < lo[a]:
            s += (lo[a] - p[a]) ** 2
        elif p[a] > hi[a]:
            s += (p[a] - hi[a]) ** 2
    return math.sqrt(s)


@njit(cache=True)
def _classify_tile(
    kind, key, T, halo, h, M, c, o_W, params, table, reach, free, levels, reach_max, nqu, nqv,
    linear, lo, hi, acc,
):  # fmt: skip
    # How the scan sees one tile (see classify_tiles).
    W = params[_k.P_W]
    H = params[_k.P_H]
    for a in range(3):  # box of the tile's voxel centres (and halo), world frame
        lo[a] = (key[a] * T + 0.5) * h
        hi[a] = ((key[a] + 1) * T - 0.5 + halo) * h
    # farthest voxel centre: every range convention is convex, so at a corner
    d_max = -np.inf
    for corner in range(8):
        x = hi[0] if corner & 1 else lo[0]
        y = hi[1] if corner & 2 else lo[1]
        z = hi[2] if corner & 4 else lo[2]
        px = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
        py = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
        pz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
        d_max = max(d_max, _k.distance(kind, params, px, py, pz))
    full_u = False
    full_v = False
    u_lo = np.inf
    u_hi = -np.inf
    v_lo = np.inf
    v_hi = -np.inf
    ring = 0.0
    if kind == _k.PINHOLE or kind == _k.ORTHOGRAPHIC:  # point-like centre of projection
        d_min = np.inf
        z_max = -np.inf
        # a pinhole's image is a pyramid: the intersection of four half-spaces through the
        # centre (u >= 0, u <= W - 1, v >= 0, v <= H - 1, each with z > 0). A box with every
        # corner outside one of them sees nothing; the test matters for boxes that cross
        # the plane z = 0, whose pixel rectangle is unbounded (the whole image below).
        out_left = True
        out_right = True
        out_top = True
        out_bottom = True
        for corner in range(8):
            x = hi[0] if corner & 1 else lo[0]
            y = hi[1] if corner & 2 else lo[1]
            z = hi[2] if corner & 4 else lo[2]
            px = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
            py = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
            pz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
            d_min = min(d_min, pz)
            z_max = max(z_max, pz)
            if kind == _k.PINHOLE:
                fu = params[_k.P_FX] * px
                fv = params[_k.P_FY] * py
                out_left &= fu + (params[_k.P_CX] + _PIXEL_SLACK) * pz < 0.0
                out_right &= fu + (params[_k.P_CX] - (W - 1.0) - _PIXEL_SLACK) * pz > 0.0
                out_top &= fv + (params[_k.P_CY] + _PIXEL_SLACK) * pz < 0.0
                out_bottom &= fv + (params[_k.P_CY] - (H - 1.0) - _PIXEL_SLACK) * pz > 0.0
            if kind == _k.ORTHOGRAPHIC:
                u = px / params[_k.P_SX] + params[_k.P_OCX]
                v = py / params[_k.P_SY] + params[_k.P_OCY]
            elif pz <= 0.0:
                full_u = True  # the box reaches behind the camera: no bound
                full_v = True
                continue
            else:
                u = params[_k.P_FX] * px / pz + params[_k.P_CX]
                v = params[_k.P_FY] * py / pz + params[_k.P_CY]
            u_lo = min(u_lo, u)
            u_hi = max(u_hi, u)
            v_lo = min(v_lo, v)
            v_hi = max(v_hi, v)
        if z_max < 0.0 or (kind == _k.PINHOLE and z_max <= 0.0):
            return OUT  # entirely behind the sensor
        if kind == _k.PINHOLE and (out_left or out_right or out_top or out_bottom):
            return OUT  # entirely beside the image's pyramid
        d_min = max(d_min, 0.0)
        if kind == _k.PINHOLE and params[_k.P_Z_CONV] == 0.0:
            d_min = _box_distance(lo, hi, o_W)
    else:
        # spherical or cylindrical: bound the tile by its circumscribed sphere
        radius = 0.5 * math.sqrt(3.0) * (hi[0] - lo[0])
        cx = 0.5 * (lo[0] + hi[0])
        cy = 0.5 * (lo[1] + hi[1])
        cz = 0.5 * (lo[2] + hi[2])
        sx = M[0, 0] * cx + M[0, 1] * cy + M[0, 2] * cz + c[0]
        sy = M[1, 0] * cx + M[1, 1] * cy + M[1, 2] * cz + c[1]
        sz = M[2, 0] * cx + M[2, 1] * cy + M[2, 2] * cz + c[2]
        rho_c = math.sqrt(sx * sx + sy * sy)
        dist = math.sqrt(rho_c * rho_c + sz * sz)
        if kind == _k.CYLINDRICAL and params[_k.P_RADIAL] != 0.0:
            d_min = max(0.0, rho_c - radius)
        else:
            d_min = _box_distance(lo, hi, o_W)
        if rho_c <= radius:
            full_u = True
        else:
            delta = math.asin(radius / rho_c)
            daz = params[_k.P_DAZ]
            ring = 2.0 * math.pi / daz
            a0 = (math.atan2(sy, sx) - delta - params[_k.P_AZ_MIN]) % (2.0 * math.pi)
            u_lo = a0 / daz
            u_hi = (a0 + 2.0 * delta) / daz
        if kind == _k.CYLINDRICAL and params[_k.P_LINEAR] != 0.0:
            v_lo = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * (sz + radius)
            v_hi = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * (sz - radius)
        elif dist <= radius:
            full_v = True
        else:
            theta = math.asin(radius / dist)
            el_c = math.atan2(sz, rho_c)
            el_hi = el_c + theta
            el_lo = el_c - theta
            if kind == _k.SPHERICAL:
                if params[_k.P_HAS_TABLE] != 0.0:
                    v_lo = _k._row_from_table(table, int(H), el_hi)
                    v_hi = _k._row_from_table(table, int(H), el_lo)
                else:
                    v_lo = (params[_k.P_EL_MAX] - el_hi) / params[_k.P_DEL]
                    v_hi = (params[_k.P_EL_MAX] - el_lo) / params[_k.P_DEL]
            elif el_hi >= 0.5 * math.pi or el_lo <= -0.5 * math.pi:
                full_v = True
            else:
                v_lo = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * math.tan(el_hi)
                v_hi = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * math.tan(el_lo)
    if d_min - _DIST_SLACK > reach_max:
        return OUT
    wraps = _k.wraps(kind, params)
    if full_u:
        u_lo = 0.0
        u_hi = float(nqu)
        ring = 0.0
    if full_v:
        v_lo = 0.0
        v_hi = float(nqv)
    if not _rect_stats(
        _NO_BOUNDS, reach, free, levels, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc
    ):
        return OUT
    if acc[0] < d_min - _DIST_SLACK:
        return OUT
    # every voxel centre projects inside the image, onto valid quads, in front of the band?
    inside_u = wraps or (
        not full_u and u_lo - _PIXEL_SLACK >= 0.0 and u_hi + _PIXEL_SLACK <= W - 1.0
    )
    inside_v = not full_v and v_lo - _PIXEL_SLACK >= 0.0 and v_hi + _PIXEL_SLACK <= H - 1.0
    if linear and inside_u and inside_v and d_max < acc[1] - _DIST_SLACK:
        return FREE
    return PARTIAL


@njit(cache=True, inline="always")
def _classify_part(
    key, S, h, M, c, o_W, params, table, bounds, reach, free, levels, reach_max, nqu, nqv,
    linear, lo, hi, acc,
):  # fmt: skip
    # How a spherical sensor sees the box of voxel centres of part ``key`` (S^3 voxels): the
    # outcomes of _classify_tile from a tighter footprint. The pixel rectangle bounds the
    # angles of the box itself, not of its circumscribed sphere: the azimuths of its corners
    # (a convex polygon clear of the axis spans less than half a turn, its extremes at
    # corners) and the elevations of its extreme heights at its nearest and farthest
    # distances from the axis; a small rectangle is folded quad by quad (_rect_stats).
    # A part whose nearest point lies beyond every quad's reach under it is OUT (occluded).
    W = params[_k.P_W]
    H = params[_k.P_H]
    for a in range(3):
        lo[a] = (key[a] * S + 0.5) * h
        hi[a] = ((key[a] + 1) * S - 0.5) * h
    d_min = _box_distance(lo, hi, o_W)
    if d_min - _DIST_SLACK > reach_max:
        return OUT
    d_max = 0.0
    x_lo = y_lo = z_lo = np.inf
    x_hi = y_hi = z_hi = -np.inf
    rho_hi = 0.0
    az0 = 0.0
    da_lo = 0.0
    da_hi = 0.0
    # the corners in pairs along z: a level pose's pair shares its sensor-frame x and y, so
    # its azimuth and distance from the axis are computed once (a zero's sign aside, which
    # changes neither rho nor, off the axis, the direction; on it the footprint is all
    # azimuths whatever they are)
    for corner in range(4):
        x = hi[0] if corner & 1 else lo[0]
        y = hi[1] if corner & 2 else lo[1]
        px_lo = py_lo = 0.0
        for top in range(2):
            z = hi[2] if top else lo[2]
            px = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
            py = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
            pz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
            d_max = max(d_max, math.sqrt(px * px + py * py + pz * pz))
            x_lo, x_hi = min(x_lo, px), max(x_hi, px)
            y_lo, y_hi = min(y_lo, py), max(y_hi, py)
            z_lo, z_hi = min(z_lo, pz), max(z_hi, pz)
            if top and px == px_lo and py == py_lo:
                continue  # the same azimuth and rho as the pair's lower corner
            px_lo = px
            py_lo = py
            rho = math.sqrt(px * px + py * py)
            rho_hi = max(rho_hi, rho)
            az = math.atan2(py, px)
            if corner == 0 and top == 0:
                az0 = az
            da = az - az0  # in (-pi, pi) once wrapped: the corners span less than half a turn
            if da > math.pi:
                da -= 2.0 * math.pi
            elif da < -math.pi:
                da += 2.0 * math.pi
            da_lo = min(da_lo, da)
            da_hi = max(da_hi, da)
    # nearest distance from the axis: of the corners' box in x and y (it holds the polygon)
    gx = x_lo if x_lo > 0.0 else (-x_hi if x_hi < 0.0 else 0.0)
    gy = y_lo if y_lo > 0.0 else (-y_hi if y_hi < 0.0 else 0.0)
    rho_lo = math.sqrt(gx * gx + gy * gy)
    # elevation atan2(z, rho) grows with z, and with rho for z < 0 (falls for z > 0)
    el_hi = math.atan2(z_hi, rho_lo if z_hi >= 0.0 else rho_hi)
    el_lo = math.atan2(z_lo, rho_hi if z_lo >= 0.0 else rho_lo)
    if params[_k.P_HAS_TABLE] != 0.0:
        v_lo = _k._row_from_table(table, int(H), el_hi)
        v_hi = _k._row_from_table(table, int(H), el_lo)
    else:
        v_lo = (params[_k.P_EL_MAX] - el_hi) / params[_k.P_DEL]
        v_hi = (params[_k.P_EL_MAX] - el_lo) / params[_k.P_DEL]
    full_u = rho_lo <= _AXIS_CLEARANCE
    if full_u:
        u_lo = 0.0
        u_hi = float(nqu)
        ring = 0.0
    else:
        daz = params[_k.P_DAZ]
        ring = 2.0 * math.pi / daz
        a0 = (az0 + da_lo - params[_k.P_AZ_MIN]) % (2.0 * math.pi)
        u_lo = a0 / daz
        u_hi = (a0 + (da_hi - da_lo)) / daz
    if not _rect_stats(bounds, reach, free, levels, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
        return OUT
    if acc[0] < d_min - _DIST_SLACK:
        return OUT
    inside_u = _k.wraps(_k.SPHERICAL, params) or (
        not full_u and u_lo - _PIXEL_SLACK >= 0.0 and u_hi + _PIXEL_SLACK <= W - 1.0
    )
    inside_v = v_lo - _PIXEL_SLACK >= 0.0 and v_hi + _PIXEL_SLACK <= H - 1.0
    clear = d_min > _DIST_SLACK  # no voxel centre at the sensor (it has no pixel)
    if linear and clear and inside_u and inside_v and d_max < acc[1] - _DIST_SLACK:
        return FREE
    return PARTIAL


@njit(cache=True, parallel=True)
def _classify_many(
    kind, keys, T, halo, h, M, c, o_W, params, table, reach, free, levels, reach_max, linear,
    out,
):  # fmt: skip
    # _classify_tile for every key (kind: the sensor kind code; see classify_tiles)
    nqv = int(params[_k.P_H]) - 1
    nqu = quad_columns(kind, params)
    for n in prange(keys.shape[0]):
        lo = np.empty(3)
        hi = np.empty(3)
        acc = np.empty(3)
        out[n] = _classify_tile(
            kind, keys[n], T, halo, h, M, c, o_W, params, table, reach, free, levels,
            reach_max, nqu, nqv, linear, lo, hi, acc,
        )  # fmt: skip


def classify_tiles(
    scan: PreparedScan, grid: GridSpec, keys: np.ndarray, halo: int = 0
) -> np.ndarray:
    """How the scan sees each tile: int8 ``OUT``, ``PARTIAL`` or ``FREE`` per row of ``keys``.

    Conservative: a tile with a point the scan informs is never ``OUT``, and ``FREE`` only
    when the scan informs every point of the tile as free space (linear shape:
    contribution ``logit(rho)`` each), exactly as the voxel-by-voxel kernel would. The
    tile is the box of its voxel centres, extended by ``halo`` voxels on the upper side of
    each axis (meshing uses ``halo=1``: the cubes whose lowest corner is in the tile).
    """
    keys = np.ascontiguousarray(keys, dtype=np.int64).reshape(-1, 3)
    out = np.zeros(keys.shape[0], dtype=np.int8)
    if keys.shape[0] == 0 or not math.isfinite(scan.reach_max):
        return out
    free, reach, levels = scan.pyramid()
    _classify_many(
        scan.kind,
        keys,
        grid.tile_size,
        float(halo),
        grid.voxel_size,
        scan.M,
        scan.c,
        scan.origin_W,
        scan.params,
        scan.table,
        reach,
        free,
        levels,
        scan.reach_max,
        scan.shape == SHAPE_LINEAR,
        out,
    )
    return out


def tiles_in_view(scan: PreparedScan, grid: GridSpec, keys: np.ndarray) -> np.ndarray:
    """Boolean mask of the tiles ``keys`` (int64 (n, 3)) that the scan may inform."""
    return classify_tiles(scan, grid, keys) != OUT


# how far a scan reaches


def reach_radius(scan: PreparedScan) -> float:
    """Distance from the sensor origin beyond which the scan informs nothing (inf if unbounded)."""
    return _sphere_radius(scan.kind, scan.params, scan.reach_max)


def bounding_sphere(scan: Scan, params: FusionParams) -> tuple[np.ndarray, float]:
    """A sphere (centre, radius) outside which the scan informs nothing, in NumPy alone.

    Looser than :func:`reach_radius` (it takes the farthest range of any pixel, which bounds
    every filtered and interpolated range) but needs no kernel: the service records it when
    a scan is uploaded.
    """
    rng = scan.range_m
    finite = rng[np.isfinite(rng)]
    r_max = float(finite.max()) if finite.size else -math.inf
    if params.no_return == "free" and bool(np.isposinf(rng).any()):
        r_max = max(r_max, scan.sensor.max_range)
    origin = np.array(scan.T_W_S[:3, 3], np.float64)
    if not math.isfinite(r_max):
        return origin, 0.0
    noise = scan.noise if scan.noise is not None else params.noise
    eps = noise.eps + noise.eps_per_m * r_max
    falloff = noise.falloff if noise.falloff is not None else eps
    kind, sensor_params, _ = scan.sensor.kernel_args()
    return origin, _sphere_radius(kind, sensor_params, widened(r_max + eps + falloff))


def _sphere_radius(kind: int, p: np.ndarray, reach: float) -> float:
    """The largest distance from the origin of a point at ``reach`` in the sensor's range."""
    if kind == _k.SPHERICAL:
        return reach
    if kind == _k.CYLINDRICAL:
        ray = p[_k.P_RADIAL] == 0.0 and p[_k.P_LINEAR] == 0.0
        return reach if ray else math.inf
    if kind == _k.PINHOLE:
        if p[_k.P_Z_CONV] == 0.0:
            return reach
        # |p| = z * |(xn, yn, 1)|, largest at an image corner
        xn = max(abs(-p[_k.P_CX]), abs(p[_k.P_W] - 1 - p[_k.P_CX])) / p[_k.P_FX]
        yn = max(abs(-p[_k.P_CY]), abs(p[_k.P_H] - 1 - p[_k.P_CY])) / p[_k.P_FY]
        return reach * math.sqrt(1.0 + xn * xn + yn * yn)
    return math.inf
