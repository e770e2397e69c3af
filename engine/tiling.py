"""Which tiles a scan creates, and how it sees each tile (DESIGN.md invariants 1, 3, 4).

Two tile sets are defined per scan, each a function of that scan alone (so the
volume does not depend on the order in which scans arrive):

* :func:`classify_tiles` says how the scan sees given tiles: ``OUT`` (it
  informs none of their voxels), ``FREE`` (it informs every voxel, all in free
  space in front of the surface band: the same contribution ``logit(rho)`` for
  each) or ``PARTIAL`` (the fusion kernel decides voxel by voxel). The test is
  conservative: the tile's box of voxel centres is bounded by a pixel
  rectangle (exact corner projection for pinhole and orthographic sensors, the
  circumscribed sphere for spherical and cylindrical ones) and compared with
  block statistics of the pixel quads under it (farthest informed distance,
  nearest range, all quads valid; :func:`engine._sampling.quad_blocks`). A tile
  is *in view* unless it is ``OUT``.
* :func:`tiles_touched` enumerates the tiles a scan *allocates*. Mapping mode:
  the tiles that the band ``[-eps - margin, eps + falloff]`` around the
  measured surface touches. Blocks of pixel quads are covered by the box of
  their band points when that box spans at most two tiles per axis, quad by
  quad otherwise (quads wider than half a tile are subdivided). No-return
  pixels carve free space but have no surface, so their quads allocate
  nothing. Closed mode: the tiles of the region of interest that are in view.

Kernels are compiled per sensor kind (the kind is a closure constant), so the
branches of the other models cost nothing. Tile keys are int64 (n, 3).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from ._sampling import COARSE, QUAD_BLOCK, quad_columns, quad_ranges
from .certainty import SHAPE_LINEAR
from .defaults import BAND_MARGIN_VOX
from .grid import GridSpec, unique_keys
from .scans import FusionParams, PreparedScan, Scan

__all__ = [
    "FREE",
    "OUT",
    "PARTIAL",
    "bounding_sphere",
    "classify_tiles",
    "reach_radius",
    "tiles_in_view",
    "tiles_touched",
]

OUT = 0
PARTIAL = 1
FREE = 2

#: Smallest piece of a quad (per side) that allocation subdivides to; it bounds the cost of
#: depth-discontinuity quads (beyond it the covering boxes just grow).
_MIN_PIECE = 1.0 / 64.0
#: Depth of the subdivision stack (two entries per halving).
_STACK = 32
#: Quads per side of the blocks that allocation covers with one box when it can.
_BAND_BLOCK = 4
#: Slack, in pixels and metres, added to the conservative tests against rounding.
_PIXEL_SLACK = 1e-3
_DIST_SLACK = 1e-9
#: Voxels: a band box reaching this close to a voxel centre counts as holding it.
_CENTRE_SLACK = 1e-6


# --------------------------------------------------------------------------------------------
# how a scan sees a tile


@njit(cache=True)
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


@njit(cache=True)
def _fold(acc, far, close, ok):
    acc[0] = max(acc[0], far)
    acc[1] = min(acc[1], close)
    if not ok:
        acc[2] = 0.0


@njit(cache=True)
def _blocks(reach, near, valid, coarse, qu0, qu1, qv0, qv1, acc):
    """Fold the block statistics over quads [qu0, qu1] x [qv0, qv1] into ``acc``
    (farthest reach, nearest range, all valid), reading the coarse level for whole cells."""
    creach, cnear, cvalid = coarse
    bv0, bv1 = qv0 // QUAD_BLOCK, qv1 // QUAD_BLOCK
    bu0, bu1 = qu0 // QUAD_BLOCK, qu1 // QUAD_BLOCK
    for cv in range(bv0 // COARSE, bv1 // COARSE + 1):
        v0 = max(bv0, cv * COARSE)
        v1 = min(bv1, cv * COARSE + COARSE - 1)
        rows_whole = v0 == cv * COARSE and v1 == cv * COARSE + COARSE - 1
        for cu in range(bu0 // COARSE, bu1 // COARSE + 1):
            u0 = max(bu0, cu * COARSE)
            u1 = min(bu1, cu * COARSE + COARSE - 1)
            if rows_whole and u0 == cu * COARSE and u1 == cu * COARSE + COARSE - 1:
                _fold(acc, creach[cv, cu], cnear[cv, cu], cvalid[cv, cu])
                continue
            for bv in range(v0, v1 + 1):
                for bu in range(u0, u1 + 1):
                    _fold(acc, reach[bv, bu], near[bv, bu], valid[bv, bu])


@njit(cache=True)
def _rect_stats(reach, near, valid, coarse, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
    """Block statistics under a pixel rectangle, into ``acc`` (see :func:`_blocks`).

    ``ring > 0`` means columns are azimuth-periodic with that many columns per full turn;
    ``u_lo`` is then in ``[0, ring)`` and ``u_hi`` may exceed ``ring`` (the interval wraps).
    Returns False when the rectangle covers no quad.
    """
    acc[0] = -np.inf
    acc[1] = np.inf
    acc[2] = 1.0
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
        _blocks(reach, near, valid, coarse, qu0, qu1, qv0, qv1, acc)
        any_quad = True
    if ring > 0.0 and hi >= ring:
        qu0, qu1 = _clip_quads(0.0, hi - ring, nqu)
        if qu1 >= qu0:
            _blocks(reach, near, valid, coarse, qu0, qu1, qv0, qv1, acc)
            any_quad = True
    return any_quad


@njit(cache=True)
def _box_distance(lo, hi, p):
    s = 0.0
    for a in range(3):
        if p[a] < lo[a]:
            s += (lo[a] - p[a]) ** 2
        elif p[a] > hi[a]:
            s += (p[a] - hi[a]) ** 2
    return math.sqrt(s)


@functools.cache
def _classify_kernel(kind: int):
    """Tile classification compiled for one sensor kind (see :func:`classify_tiles`)."""
    pointlike = kind in (_k.PINHOLE, _k.ORTHOGRAPHIC)

    @njit(cache=True)
    def classify(
        key,
        T,
        halo,
        h,
        M,
        c,
        o_W,
        params,
        table,
        reach,
        near,
        valid,
        coarse,
        reach_max,
        nqu,
        nqv,
        eps0,
        eps1,
        linear,
        lo,
        hi,
        acc,
    ):
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
        if pointlike:
            d_min = np.inf
            z_max = -np.inf
            for corner in range(8):
                x = hi[0] if corner & 1 else lo[0]
                y = hi[1] if corner & 2 else lo[1]
                z = hi[2] if corner & 4 else lo[2]
                px = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
                py = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
                pz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
                d_min = min(d_min, pz)
                z_max = max(z_max, pz)
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
                        v_lo = _k._row_from_table(table, el_hi)
                        v_hi = _k._row_from_table(table, el_lo)
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
        if not _rect_stats(reach, near, valid, coarse, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
            return OUT
        if acc[0] < d_min - _DIST_SLACK:
            return OUT
        # every voxel centre projects inside the image, onto valid quads, in front of the band?
        inside_u = wraps or (
            not full_u and u_lo - _PIXEL_SLACK >= 0.0 and u_hi + _PIXEL_SLACK <= W - 1.0
        )
        inside_v = not full_v and v_lo - _PIXEL_SLACK >= 0.0 and v_hi + _PIXEL_SLACK <= H - 1.0
        if (
            linear
            and inside_u
            and inside_v
            and acc[2] != 0.0
            and d_max < acc[1] * (1.0 - eps1) - eps0 - _DIST_SLACK
        ):
            return FREE
        return PARTIAL

    @njit(cache=True, parallel=True)
    def classify_many(
        keys,
        T,
        halo,
        h,
        M,
        c,
        o_W,
        params,
        table,
        reach,
        near,
        valid,
        coarse,
        reach_max,
        eps0,
        eps1,
        linear,
        out,
    ):
        nqv = int(params[_k.P_H]) - 1
        nqu = quad_columns(kind, params)
        for n in prange(keys.shape[0]):
            lo = np.empty(3)
            hi = np.empty(3)
            acc = np.empty(3)
            out[n] = classify(
                keys[n],
                T,
                halo,
                h,
                M,
                c,
                o_W,
                params,
                table,
                reach,
                near,
                valid,
                coarse,
                reach_max,
                nqu,
                nqv,
                eps0,
                eps1,
                linear,
                lo,
                hi,
                acc,
            )

    return classify_many


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
    _classify_kernel(scan.kind)(
        keys,
        grid.tile_size_vox,
        float(halo),
        grid.voxel_size_m,
        scan.M,
        scan.c,
        scan.origin_W,
        scan.params,
        scan.table,
        scan.reach,
        scan.near,
        scan.valid,
        scan.coarse,
        scan.reach_max,
        scan.eps0,
        scan.eps1,
        scan.shape == SHAPE_LINEAR,
        out,
    )
    return out


def tiles_in_view(scan: PreparedScan, grid: GridSpec, keys: np.ndarray) -> np.ndarray:
    """Boolean mask of the tiles ``keys`` (int64 (n, 3)) that the scan may inform."""
    return classify_tiles(scan, grid, keys) != OUT


# --------------------------------------------------------------------------------------------
# allocation: mapping mode


@njit(cache=True)
def _tile_range(box, h, T):
    """Tile index ranges (inclusive) of the voxel centres in a box (x0, y0, z0, x1, y1, z1)
    widened to the next voxel centre outside it on each side (less than a voxel of slack)."""
    return (
        int(math.floor(box[0] / h - 0.5 + _CENTRE_SLACK)) // T,
        int(math.floor(box[1] / h - 0.5 + _CENTRE_SLACK)) // T,
        int(math.floor(box[2] / h - 0.5 + _CENTRE_SLACK)) // T,
        int(math.ceil(box[3] / h - 0.5 - _CENTRE_SLACK)) // T,
        int(math.ceil(box[4] / h - 0.5 - _CENTRE_SLACK)) // T,
        int(math.ceil(box[5] / h - 0.5 - _CENTRE_SLACK)) // T,
    )


@njit(cache=True)
def _emit(rng6, keys, count, fill, prev):
    """Emit the tiles of a key range, skipping a range equal to the previous one (``prev``,
    six ints, updated): neighbouring quads mostly repeat it."""
    same = True
    for k in range(6):
        if rng6[k] != prev[k]:
            same = False
        prev[k] = rng6[k]
    if same:
        return count
    for a in range(rng6[0], rng6[3] + 1):
        for b in range(rng6[1], rng6[4] + 1):
            for c in range(rng6[2], rng6[5] + 1):
                if fill:
                    keys[count, 0] = a
                    keys[count, 1] = b
                    keys[count, 2] = c
                count += 1
    return count


@njit(cache=True, inline="always")
def _grow(box, pts, v, u):
    for e in range(2):
        for ax in range(3):
            box[ax] = min(box[ax], pts[v, u, e, ax])
            box[3 + ax] = max(box[3 + ax], pts[v, u, e, ax])


@njit(cache=True, inline="always")
def _reset(box):
    for ax in range(3):
        box[ax] = np.inf
        box[3 + ax] = -np.inf


@functools.cache
def _band_kernels(kind: int):
    """Band-allocation kernels compiled for one sensor kind (see :func:`tiles_touched`)."""

    @njit(cache=True, inline="always")
    def world(R, t, params, table, u, v, d, out, row):
        x, y, z = _k.unproject_point(kind, params, table, u, v, d)
        for a in range(3):
            out[row, a] = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z + t[a]

    @njit(cache=True, parallel=True)
    def band_points(rng, params, table, R, t, eps0, eps1, falloff, margin, out):
        # world points of every pixel at both ends of its band, out (H, W, 2, 3)
        H, W = rng.shape
        for v in prange(H):
            for u in range(W):
                r = rng[v, u]
                if math.isnan(r):
                    continue
                eps = eps0 + eps1 * r
                f = falloff if falloff > 0.0 else eps
                uf = float(u)
                vf = float(v)
                world(R, t, params, table, uf, vf, max(r - eps - margin, 0.0), out[v, u], 0)
                world(R, t, params, table, uf, vf, r + eps + f, out[v, u], 1)

    @njit(cache=True)
    def node_points(
        rng, pts, qu, qv, a0, a1, b0, b1, params, table, R, t, eps0, eps1, falloff, margin, corners
    ):
        # band-end points of the corners of the sub-quad [a0, a1] x [b0, b1] of quad (qu, qv):
        # rows 0..3 at the near end, 4..7 at the far end; row k has du = k & 1, dv = k >> 1
        if a0 == 0.0 and a1 == 1.0 and b0 == 0.0 and b1 == 1.0:
            qu1 = qu + 1 if qu + 1 < rng.shape[1] else 0
            for e in range(2):
                for ax in range(3):
                    corners[4 * e + 0, ax] = pts[qv, qu, e, ax]
                    corners[4 * e + 1, ax] = pts[qv, qu1, e, ax]
                    corners[4 * e + 2, ax] = pts[qv + 1, qu, e, ax]
                    corners[4 * e + 3, ax] = pts[qv + 1, qu1, e, ax]
            return
        qu1 = qu + 1 if qu + 1 < rng.shape[1] else 0
        r00 = rng[qv, qu]
        r01 = rng[qv, qu1]
        r10 = rng[qv + 1, qu]
        r11 = rng[qv + 1, qu1]
        for k in range(4):
            fu = a1 if k & 1 else a0
            fv = b1 if k >> 1 else b0
            r = (1.0 - fv) * ((1.0 - fu) * r00 + fu * r01) + fv * ((1.0 - fu) * r10 + fu * r11)
            eps = eps0 + eps1 * r
            f = falloff if falloff > 0.0 else eps
            world(R, t, params, table, qu + fu, qv + fv, max(r - eps - margin, 0.0), corners, k)
            world(R, t, params, table, qu + fu, qv + fv, r + eps + f, corners, 4 + k)

    @njit(cache=True)
    def quad_tiles(
        rng,
        pts,
        qu,
        qv,
        params,
        table,
        R,
        t,
        eps0,
        eps1,
        falloff,
        margin,
        h,
        T,
        fill,
        keys,
        count,
        prev,
        corners,
        box,
        stack,
    ):
        # Cover the band of one valid quad with boxes spanning at most two tiles per axis,
        # halving the quad (across its wider side) where its box is larger.
        stack[0, 0] = 0.0
        stack[0, 1] = 1.0
        stack[0, 2] = 0.0
        stack[0, 3] = 1.0
        top = 1
        while top > 0:
            top -= 1
            a0 = stack[top, 0]
            a1 = stack[top, 1]
            b0 = stack[top, 2]
            b1 = stack[top, 3]
            node_points(
                rng,
                pts,
                qu,
                qv,
                a0,
                a1,
                b0,
                b1,
                params,
                table,
                R,
                t,
                eps0,
                eps1,
                falloff,
                margin,
                corners,
            )
            _reset(box)
            for k in range(8):
                for ax in range(3):
                    box[ax] = min(box[ax], corners[k, ax])
                    box[3 + ax] = max(box[3 + ax], corners[k, ax])
            span = _tile_range(box, h, T)
            small = span[3] - span[0] <= 1 and span[4] - span[1] <= 1 and span[5] - span[2] <= 1
            wide_u = 0.0
            wide_v = 0.0
            for ax in range(3):
                wide_u += (corners[5, ax] - corners[4, ax]) ** 2
                wide_v += (corners[6, ax] - corners[4, ax]) ** 2
            # the band's depth cannot shrink by halving the quad: stop once it is narrow
            narrow = max(wide_u, wide_v) <= (0.5 * T * h) ** 2
            if (
                small
                or narrow
                or a1 - a0 < _MIN_PIECE
                or b1 - b0 < _MIN_PIECE
                or top + 2 > stack.shape[0]
            ):
                count = _emit(span, keys, count, fill, prev)
                continue
            for half in range(2):
                if wide_u >= wide_v:
                    mid = 0.5 * (a0 + a1)
                    stack[top, 0] = a0 if half == 0 else mid
                    stack[top, 1] = mid if half == 0 else a1
                    stack[top, 2] = b0
                    stack[top, 3] = b1
                else:
                    mid = 0.5 * (b0 + b1)
                    stack[top, 0] = a0
                    stack[top, 1] = a1
                    stack[top, 2] = b0 if half == 0 else mid
                    stack[top, 3] = mid if half == 0 else b1
                top += 1
        return count

    @njit(cache=True, parallel=True)
    def band_tiles(
        rng,
        pts,
        params,
        table,
        R,
        t,
        eps0,
        eps1,
        falloff,
        max_disc,
        margin,
        h,
        T,
        fill,
        offsets,
        keys,
    ):
        nqv = rng.shape[0] - 1
        nqu = quad_columns(kind, params)
        W = rng.shape[1]
        nbv = -(-nqv // _BAND_BLOCK)
        nbu = -(-nqu // _BAND_BLOCK)
        for bv in prange(nbv):
            count = offsets[bv]
            prev = np.full(6, np.iinfo(np.int64).min, np.int64)
            corners = np.empty((8, 3))
            box = np.empty(6)
            stack = np.empty((_STACK, 4))
            qv0 = bv * _BAND_BLOCK
            qv1 = min(nqv, qv0 + _BAND_BLOCK)
            for bu in range(nbu):
                qu0 = bu * _BAND_BLOCK
                qu1 = min(nqu, qu0 + _BAND_BLOCK)
                # box of the band points of every valid quad of the block
                _reset(box)
                n_valid = 0
                for qv in range(qv0, qv1):
                    for qu in range(qu0, qu1):
                        if not quad_ranges(rng, qu, qv, max_disc)[4]:
                            continue
                        n_valid += 1
                        u1 = qu + 1 if qu + 1 < W else 0
                        _grow(box, pts, qv, qu)
                        _grow(box, pts, qv, u1)
                        _grow(box, pts, qv + 1, qu)
                        _grow(box, pts, qv + 1, u1)
                if n_valid == 0:
                    continue
                span = _tile_range(box, h, T)
                if span[3] - span[0] <= 1 and span[4] - span[1] <= 1 and span[5] - span[2] <= 1:
                    count = _emit(span, keys, count, fill, prev)
                    continue
                for qv in range(qv0, qv1):
                    for qu in range(qu0, qu1):
                        if quad_ranges(rng, qu, qv, max_disc)[4]:
                            count = quad_tiles(
                                rng,
                                pts,
                                qu,
                                qv,
                                params,
                                table,
                                R,
                                t,
                                eps0,
                                eps1,
                                falloff,
                                margin,
                                h,
                                T,
                                fill,
                                keys,
                                count,
                                prev,
                                corners,
                                box,
                                stack,
                            )
            if not fill:
                offsets[bv] = count

    return band_points, band_tiles


def _band_tile_keys(scan: PreparedScan, grid: GridSpec) -> np.ndarray:
    h = grid.voxel_size_m
    T = grid.tile_size_vox
    margin = BAND_MARGIN_VOX * h
    R = np.ascontiguousarray(scan.T_W_S[:3, :3])
    t = np.ascontiguousarray(scan.T_W_S[:3, 3])
    rng = scan.surface_m
    band_points, band_tiles = _band_kernels(scan.kind)
    pts = np.full((*rng.shape, 2, 3), np.nan)
    band_points(rng, scan.params, scan.table, R, t, scan.eps0, scan.eps1, scan.falloff, margin, pts)
    n_rows = -(-(rng.shape[0] - 1) // _BAND_BLOCK)
    counts = np.zeros(n_rows, np.int64)
    args = (
        rng,
        pts,
        scan.params,
        scan.table,
        R,
        t,
        scan.eps0,
        scan.eps1,
        scan.falloff,
        scan.max_disc,
        margin,
        h,
        T,
    )
    band_tiles(*args, False, counts, np.zeros((0, 3), np.int64))
    offsets = np.zeros(n_rows, np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    keys = np.empty((int(counts.sum()), 3), np.int64)
    band_tiles(*args, True, offsets, keys)
    return unique_keys(keys)


# --------------------------------------------------------------------------------------------
# allocation: closed mode, and the common entry point


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
    eps = noise.eps_m + noise.eps_per_m * r_max
    falloff = noise.falloff_m if noise.falloff_m is not None else eps
    kind, sensor_params, _ = scan.sensor.kernel_args()
    return origin, _sphere_radius(kind, sensor_params, r_max + eps + falloff)


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


def _roi_tiles_in_view(scan: PreparedScan, grid: GridSpec) -> np.ndarray:
    lo, hi = grid.roi_tiles()
    radius = reach_radius(scan)
    if math.isfinite(radius):
        tile_m = grid.tile_size_m
        o = scan.origin_W
        lo = np.maximum(lo, np.floor((o - radius) / tile_m).astype(np.int64) - 1)
        hi = np.minimum(hi, np.floor((o + radius) / tile_m).astype(np.int64) + 2)
    if np.any(hi <= lo):
        return np.zeros((0, 3), np.int64)
    axes = [np.arange(lo[a], hi[a], dtype=np.int64) for a in range(3)]
    keys = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return keys[tiles_in_view(scan, grid, keys)]


def _inside_roi(grid: GridSpec, keys: np.ndarray) -> np.ndarray:
    lo, hi = grid.roi_tiles()
    return np.all((keys >= lo) & (keys < hi), axis=1)


def tiles_touched(scan: PreparedScan, grid: GridSpec) -> np.ndarray:
    """Keys (int64 (n, 3), sorted, unique) of the tiles this scan allocates.

    Mapping mode: tiles near the measured surface (the band ``[-eps - margin, eps + falloff]``
    around every valid pixel quad; with bounds, only tiles of the region of interest).
    Closed mode: tiles of the region of interest in view of the scan.
    """
    if not math.isfinite(scan.reach_max):
        return np.zeros((0, 3), np.int64)
    if grid.mode == "closed":
        return _roi_tiles_in_view(scan, grid)
    keys = _band_tile_keys(scan, grid)
    if grid.bounds_m is not None:
        keys = keys[_inside_roi(grid, keys)]
    return keys
