"""Which tiles a scan creates, and which tiles it can inform (DESIGN.md invariants 1, 3, 4).

Two tile sets are defined per scan, each a function of that scan alone (so the
volume does not depend on the order in which scans arrive):

* :func:`tiles_in_view` tests given tiles: a tile is *in view* when some of
  its voxels may be informed by the scan. The test is conservative (it never
  drops a tile with an informed voxel): the tile's bounding box is projected
  into a pixel rectangle, and the tile is kept when the farthest informed
  distance over the quads of that rectangle (the reach map of
  :func:`engine.scans.prepare_scan`) reaches the nearest point of the tile.
  The fusion kernel then decides voxel by voxel.
* :func:`tiles_touched` enumerates the tiles a scan *allocates*. Mapping mode:
  the tiles that the band ``[-eps - margin, eps + falloff]`` around the
  measured surface touches, found by covering every valid pixel quad with
  boxes (quads wider than half a tile are subdivided). No-return pixels carve
  free space but have no surface, so their quads allocate nothing. Closed mode: the tiles
  of the region of interest that are in view (a line of sight crosses them up
  to the end of its surface band).

Tiles are keyed by integer index ``(a, b, c)``; arrays of keys are int64 (n, 3).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from ._sampling import REACH_BLOCK, quad_columns, quad_ranges
from .defaults import BAND_MARGIN_VOX
from .grid import GridSpec
from .scans import PreparedScan

__all__ = ["tiles_in_view", "tiles_touched"]

#: Most subdivisions of a quad per side when covering its band (bounds the cost of
#: depth-discontinuity quads; beyond it the covering boxes just grow).
_MAX_SUBDIVISIONS = 64
#: Slack, in pixels and metres, added to the conservative tests against rounding.
_PIXEL_SLACK = 1e-3
_DIST_SLACK = 1e-9


# --------------------------------------------------------------------------------------------
# view test


@njit(cache=True)
def _block_max_over_quads(reach, qu0, qu1, qv0, qv1):
    best = -np.inf
    for bv in range(qv0 // REACH_BLOCK, qv1 // REACH_BLOCK + 1):
        for bu in range(qu0 // REACH_BLOCK, qu1 // REACH_BLOCK + 1):
            if reach[bv, bu] > best:
                best = reach[bv, bu]
    return best


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
def _reach_over_rect(kind, params, table, reach, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring):
    """Largest informed distance over the quads under a pixel rectangle.

    ``ring > 0`` means columns are azimuth-periodic with that many columns per full turn;
    ``u_lo`` is then in ``[0, ring)`` and ``u_hi`` may exceed ``ring`` (the interval wraps).
    """
    qv0, qv1 = _clip_quads(v_lo - _PIXEL_SLACK, v_hi + _PIXEL_SLACK, nqv)
    if qv1 < qv0:
        return -np.inf
    best = -np.inf
    lo = u_lo - _PIXEL_SLACK
    hi = u_hi + _PIXEL_SLACK
    if ring > 0.0 and lo < 0.0:
        lo += ring
        hi += ring
    qu0, qu1 = _clip_quads(lo, hi, nqu)
    if qu1 >= qu0:
        best = _block_max_over_quads(reach, qu0, qu1, qv0, qv1)
    if ring > 0.0 and hi >= ring:
        qu0, qu1 = _clip_quads(0.0, hi - ring, nqu)
        if qu1 >= qu0:
            best = max(best, _block_max_over_quads(reach, qu0, qu1, qv0, qv1))
    return best


@njit(cache=True)
def _box_distance(lo, hi, p):
    s = 0.0
    for a in range(3):
        if p[a] < lo[a]:
            s += (lo[a] - p[a]) ** 2
        elif p[a] > hi[a]:
            s += (p[a] - hi[a]) ** 2
    return math.sqrt(s)


@njit(cache=True)
def _tile_in_view(key, T, h, M, c, o_W, kind, params, table, reach, reach_max, nqu, nqv):
    # Box of the tile's voxel centres, world frame.
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = (key[a] * T + 0.5) * h
        hi[a] = ((key[a] + 1) * T - 0.5) * h
    full_u = False
    full_v = False
    u_lo = 0.0
    u_hi = 0.0
    v_lo = 0.0
    v_hi = 0.0
    ring = 0.0
    if kind == _k.PINHOLE or kind == _k.ORTHOGRAPHIC:
        d_min = np.inf
        behind = False
        u_lo = np.inf
        u_hi = -np.inf
        v_lo = np.inf
        v_hi = -np.inf
        z_max = -np.inf
        for corner in range(8):
            x = hi[0] if corner & 1 else lo[0]
            y = hi[1] if corner & 2 else lo[1]
            z = hi[2] if corner & 4 else lo[2]
            px = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
            py = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
            pz = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
            z_max = max(z_max, pz)
            d_min = min(d_min, pz)
            if kind == _k.ORTHOGRAPHIC:
                u = px / params[_k.P_SX] + params[_k.P_OCX]
                v = py / params[_k.P_SY] + params[_k.P_OCY]
            elif pz <= 0.0:
                behind = True
                continue
            else:
                u = params[_k.P_FX] * px / pz + params[_k.P_CX]
                v = params[_k.P_FY] * py / pz + params[_k.P_CY]
            u_lo = min(u_lo, u)
            u_hi = max(u_hi, u)
            v_lo = min(v_lo, v)
            v_hi = max(v_hi, v)
        if z_max < 0.0:
            return False
        if behind:
            full_u = True
            full_v = True
        if d_min < 0.0:
            d_min = 0.0
        if kind == _k.PINHOLE and params[_k.P_Z_CONV] == 0.0:
            d_min = _box_distance(lo, hi, o_W)
    else:
        # Spherical or cylindrical: bound the tile by its circumscribed sphere.
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
        # azimuth: columns
        if rho_c <= radius:
            full_u = True
        else:
            delta = math.asin(radius / rho_c)
            daz = params[_k.P_DAZ]
            ring = 2.0 * math.pi / daz
            a = (math.atan2(sy, sx) - delta - params[_k.P_AZ_MIN]) % (2.0 * math.pi)
            u_lo = a / daz
            u_hi = (a + 2.0 * delta) / daz
        # elevation: rows
        linear = kind == _k.CYLINDRICAL and params[_k.P_LINEAR] != 0.0
        if linear:
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
            else:
                half_pi = 0.5 * math.pi
                if el_hi >= half_pi or el_lo <= -half_pi:
                    full_v = True
                else:
                    v_lo = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * math.tan(el_hi)
                    v_hi = params[_k.P_CYL_CY] - params[_k.P_CYL_FY] * math.tan(el_lo)
    if d_min - _DIST_SLACK > reach_max:
        return False
    if full_u:
        u_lo = 0.0
        u_hi = float(nqu)
        ring = 0.0
    if full_v:
        v_lo = 0.0
        v_hi = float(nqv)
    best = _reach_over_rect(kind, params, table, reach, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring)
    return best >= d_min - _DIST_SLACK


@njit(cache=True, parallel=True)
def _tiles_in_view(keys, T, h, M, c, o_W, kind, params, table, reach, reach_max, out):
    nqv = int(params[_k.P_H]) - 1
    nqu = quad_columns(kind, params)
    for n in prange(keys.shape[0]):
        out[n] = _tile_in_view(
            keys[n], T, h, M, c, o_W, kind, params, table, reach, reach_max, nqu, nqv
        )


def tiles_in_view(scan: PreparedScan, grid: GridSpec, keys: np.ndarray) -> np.ndarray:
    """Boolean mask of the tiles ``keys`` (int64 (n, 3)) that the scan may inform.

    Conservative: a tile with a voxel the scan informs is always in view.
    """
    keys = np.ascontiguousarray(keys, dtype=np.int64).reshape(-1, 3)
    out = np.zeros(keys.shape[0], dtype=np.bool_)
    if keys.shape[0] == 0 or not math.isfinite(scan.reach_max):
        return out
    _tiles_in_view(
        keys,
        grid.tile_size_vox,
        grid.voxel_size_m,
        scan.M,
        scan.c,
        scan.origin_W,
        scan.kind,
        scan.params,
        scan.table,
        scan.reach,
        scan.reach_max,
        out,
    )
    return out


# --------------------------------------------------------------------------------------------
# allocation: mapping mode


@njit(cache=True)
def _world(R, t, kind, params, table, u, v, d, out, row):
    x, y, z = _k.unproject_point(kind, params, table, u, v, d)
    for a in range(3):
        out[row, a] = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z + t[a]


@njit(cache=True)
def _emit_box(lo, hi, h, T, keys, count, fill, last):
    """Emit the tiles holding voxel centres within one voxel of the box [lo, hi]."""
    t0 = np.empty(3, np.int64)
    t1 = np.empty(3, np.int64)
    for a in range(3):
        i_lo = int(math.ceil(lo[a] / h - 0.5)) - 1
        i_hi = int(math.floor(hi[a] / h - 0.5)) + 1
        t0[a] = i_lo // T
        t1[a] = i_hi // T
    for a in range(t0[0], t1[0] + 1):
        for b in range(t0[1], t1[1] + 1):
            for cc in range(t0[2], t1[2] + 1):
                if a == last[0] and b == last[1] and cc == last[2]:
                    continue
                if fill:
                    keys[count, 0] = a
                    keys[count, 1] = b
                    keys[count, 2] = cc
                last[0] = a
                last[1] = b
                last[2] = cc
                count += 1
    return count


@njit(cache=True, parallel=True)
def _band_tiles(
    rng, kind, params, table, R, t, eps0, eps1, falloff, max_disc, margin, h, T, fill, offsets, keys
):
    nqv = rng.shape[0] - 1
    nqu = quad_columns(kind, params)
    half_tile = 0.5 * T * h
    for qv in prange(nqv):
        count = offsets[qv]
        last = np.full(3, np.iinfo(np.int64).min, np.int64)
        corners = np.empty((8, 3))
        sub = np.empty((8, 3))
        lo = np.empty(3)
        hi = np.empty(3)
        rc = np.empty(4)
        for qu in range(nqu):
            r00, r01, r10, r11, ok = quad_ranges(rng, qu, qv, max_disc)
            if not ok:
                continue
            rc[0] = r00
            rc[1] = r01
            rc[2] = r10
            rc[3] = r11
            # corner points at both ends of the band, to size the subdivision
            for k in range(4):
                eps = eps0 + eps1 * rc[k]
                f = falloff if falloff > 0.0 else eps
                u = qu + (k & 1)
                v = qv + (k >> 1)
                _world(R, t, kind, params, table, u, v, max(rc[k] - eps - margin, 0.0), corners, k)
                _world(R, t, kind, params, table, u, v, rc[k] + eps + f, corners, 4 + k)
            ext_u = 0.0
            ext_v = 0.0
            for e in range(2):
                base = 4 * e
                for a in range(2):
                    du = 0.0
                    dv = 0.0
                    for ax in range(3):
                        du += (corners[base + 2 * a + 1, ax] - corners[base + 2 * a, ax]) ** 2
                        dv += (corners[base + 2 + a, ax] - corners[base + a, ax]) ** 2
                    ext_u = max(ext_u, math.sqrt(du))
                    ext_v = max(ext_v, math.sqrt(dv))
            n_u = min(_MAX_SUBDIVISIONS, max(1, int(math.ceil(ext_u / half_tile))))
            n_v = min(_MAX_SUBDIVISIONS, max(1, int(math.ceil(ext_v / half_tile))))
            for su in range(n_u):
                for sv in range(n_v):
                    for k in range(4):
                        fu = (su + (k & 1)) / n_u
                        fv = (sv + (k >> 1)) / n_v
                        r = (1.0 - fv) * ((1.0 - fu) * r00 + fu * r01) + fv * (
                            (1.0 - fu) * r10 + fu * r11
                        )
                        eps = eps0 + eps1 * r
                        f = falloff if falloff > 0.0 else eps
                        _world(
                            R,
                            t,
                            kind,
                            params,
                            table,
                            qu + fu,
                            qv + fv,
                            max(r - eps - margin, 0.0),
                            sub,
                            k,
                        )
                        _world(R, t, kind, params, table, qu + fu, qv + fv, r + eps + f, sub, 4 + k)
                    for ax in range(3):
                        lo[ax] = np.inf
                        hi[ax] = -np.inf
                        for k in range(8):
                            lo[ax] = min(lo[ax], sub[k, ax])
                            hi[ax] = max(hi[ax], sub[k, ax])
                    count = _emit_box(lo, hi, h, T, keys, count, fill, last)
        if not fill:
            offsets[qv] = count


def _unique_keys(keys: np.ndarray) -> np.ndarray:
    if keys.shape[0] == 0:
        return keys.reshape(0, 3)
    return np.unique(keys, axis=0)


def _band_tile_keys(scan: PreparedScan, grid: GridSpec) -> np.ndarray:
    h = grid.voxel_size_m
    T = grid.tile_size_vox
    margin = BAND_MARGIN_VOX * h
    R = np.ascontiguousarray(scan.T_W_S[:3, :3])
    t = np.ascontiguousarray(scan.T_W_S[:3, 3])
    nqv = scan.range_m.shape[0] - 1
    counts = np.zeros(nqv, np.int64)
    dummy = np.zeros((0, 3), np.int64)
    args = (
        scan.surface_m,
        scan.kind,
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
    _band_tiles(*args, False, counts, dummy)
    offsets = np.zeros(nqv, np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    keys = np.empty((int(counts.sum()), 3), np.int64)
    _band_tiles(*args, True, offsets, keys)
    return _unique_keys(keys)


def _reach_radius(scan: PreparedScan) -> float:
    """Distance from the sensor origin beyond which the scan informs nothing (inf if unbounded)."""
    p = scan.params
    if scan.kind == _k.SPHERICAL:
        return scan.reach_max
    if scan.kind == _k.CYLINDRICAL:
        ray = p[_k.P_RADIAL] == 0.0 and p[_k.P_LINEAR] == 0.0
        return scan.reach_max if ray else math.inf
    if scan.kind == _k.PINHOLE:
        if p[_k.P_Z_CONV] == 0.0:
            return scan.reach_max
        # |p| = z * |(xn, yn, 1)|, largest at an image corner
        xn = max(abs(-p[_k.P_CX]), abs(p[_k.P_W] - 1 - p[_k.P_CX])) / p[_k.P_FX]
        yn = max(abs(-p[_k.P_CY]), abs(p[_k.P_H] - 1 - p[_k.P_CY])) / p[_k.P_FY]
        return scan.reach_max * math.sqrt(1.0 + xn * xn + yn * yn)
    return math.inf


def _roi_tiles_in_view(scan: PreparedScan, grid: GridSpec) -> np.ndarray:
    lo, hi = grid.roi_tiles()
    radius = _reach_radius(scan)
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
