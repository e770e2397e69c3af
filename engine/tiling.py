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
  free-space bound; :func:`engine._sampling.bounds_and_pyramid`). A pinhole box
  with all corners outside one side of the image's pyramid is ``OUT`` too:
  a box across the sensor's plane ``z = 0`` has no bounded rectangle. A tile
  is *in view* unless it is ``OUT``.
* :func:`tiles_touched` enumerates the tiles a scan *allocates*. Mapping mode:
  the tiles that the band ``[-eps - margin, eps + falloff]`` around the
  measured surface touches: the tiles of the box of each valid pixel quad's
  band-end points. A pyramid of nodes (2 x 2 quads per level up) keeps, per
  node, a 4 x 4 x 4 tile mask of what its quads touch, so a walk from the top
  emits each region's tiles once instead of once per quad. A quad whose box
  spans more than four tiles on an axis (the band across a depth step, or seen
  edge-on) is covered by pieces: halved while wider than half a tile, then cut
  into slabs of its range interval. No-return pixels carve free space but
  have no surface, so their quads allocate nothing. Closed mode: the tiles of
  the region of interest that are in view.

Kernels are compiled per sensor kind (the kind is a closure constant), so the
branches of the other models cost nothing. Tile keys are int64 (n, 3).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from ._memory import Scratch, scratch_array
from ._sampling import (
    PYRAMID_SPAN,
    QUAD_BLOCK,
    corner_ranges,
    pyramid_levels,
    quad_columns,
    quad_valid,
    widened,
)
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
#: Tiles per axis of the masks of the allocation pyramid (4 x 4 x 4 tiles: 64 bits).
_SPAN = 4
#: ``lo_x`` of a node of the allocation pyramid whose band spans more than ``_SPAN`` tiles.
_BIG_LO = np.iinfo(np.int64).min
#: Most slabs one narrow piece of a quad's band is cut into (a bound on the work per quad).
_MAX_SLABS = 4096
#: Entries of the cache of recently emitted tile keys in allocation (a power of two).
_SEEN = 256
#: The allocation pyramid is merged up to at most this many top nodes (the parallel walk).
_TOP_NODES = 256
#: Keys each top node's walk can hold (most emit far fewer; see _band_tile_keys).
_WALK_ROOM = 1024
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


@njit(cache=True)
def _rect_stats(reach, free, levels, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
    """Block statistics under a pixel rectangle, into ``acc`` (see :func:`_blocks`).

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
        _blocks(reach, free, levels, qu0, qu1, qv0, qv1, acc)
        any_quad = True
    if ring > 0.0 and hi >= ring:
        qu0, qu1 = _clip_quads(0.0, hi - ring, nqu)
        if qu1 >= qu0:
            _blocks(reach, free, levels, qu0, qu1, qv0, qv1, acc)
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
    if not _rect_stats(reach, free, levels, u_lo, u_hi, v_lo, v_hi, nqu, nqv, ring, acc):
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


# --------------------------------------------------------------------------------------------
# allocation: mapping mode


@njit(cache=True, inline="always")
def _first_tile(x, h, T):
    """Tile of the voxel centre at or below coordinate ``x`` (less than a voxel of slack).

    Floating point, by reciprocals the compiler hoists out of loops (a division costs tens
    of cycles): ``floor(y / T)`` equals ``floor(floor(y) / T)`` but for rounding when ``y``
    is within an ulp of an integer, and the voxel such rounding can drop is the one the
    widening adds outside the box."""
    return int(math.floor((x * (1.0 / h) - 0.5 + _CENTRE_SLACK) * (1.0 / T)))


@njit(cache=True, inline="always")
def _last_tile(x, h, T):
    """Tile of the voxel centre at or above coordinate ``x`` (see :func:`_first_tile`)."""
    return int(math.floor(math.ceil(x * (1.0 / h) - 0.5 - _CENTRE_SLACK) * (1.0 / T)))


@njit(cache=True, inline="always")
def _tile_range(box, h, T):
    """Tile index ranges (inclusive) of the voxel centres in a box (x0, y0, z0, x1, y1, z1)
    widened to the next voxel centre outside it on each side (less than a voxel of slack)."""
    return (
        _first_tile(box[0], h, T),
        _first_tile(box[1], h, T),
        _first_tile(box[2], h, T),
        _last_tile(box[3], h, T),
        _last_tile(box[4], h, T),
        _last_tile(box[5], h, T),
    )


@njit(cache=True, inline="always")
def _emit_key(a, b, c, keys, count, seen):
    """Emit tile ``(a, b, c)`` unless ``seen`` (a small direct-mapped cache of keys emitted
    lately, ``(_SEEN, 3)``) holds it: neighbouring pieces of the band mostly repeat tiles.
    Returns the count of keys emitted; the key is written to ``keys[count]`` when it fits
    (an empty ``keys`` only counts)."""
    slot = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) & (seen.shape[0] - 1)
    if seen[slot, 0] == a and seen[slot, 1] == b and seen[slot, 2] == c:
        return count
    seen[slot, 0] = a
    seen[slot, 1] = b
    seen[slot, 2] = c
    if count < keys.shape[0]:
        keys[count, 0] = a
        keys[count, 1] = b
        keys[count, 2] = c
    return count + 1


@njit(cache=True, inline="always")
def _emit(rng6, keys, count, seen):
    """Emit the tiles of a key range (see :func:`_emit_key`)."""
    for a in range(rng6[0], rng6[3] + 1):
        for b in range(rng6[1], rng6[4] + 1):
            for c in range(rng6[2], rng6[5] + 1):
                count = _emit_key(a, b, c, keys, count, seen)
    return count


@njit(cache=True, inline="always")
def _box_of(corners, box):
    """The box (x0, y0, z0, x1, y1, z1) of the 8 points ``corners``, into ``box``."""
    _box_of_ends(_extremes(corners, 0), _extremes(corners, 4), box)


@njit(cache=True, inline="always")
def _box_of_ends(near, far, box):
    """The box of two sets of points given by their :func:`_extremes`, into ``box`` (min
    and max are exact: the same box as from all the points at once)."""
    for ax in range(3):
        box[ax] = min(near[ax], far[ax])
        box[3 + ax] = max(near[3 + ax], far[3 + ax])


def _overflow_masks() -> np.ndarray:
    """``[axis, o]``: the bits of a 4 x 4 x 4 tile mask that leave it when shifted by ``o``
    tiles along ``axis`` (bit ``16 x + 4 y + z`` is tile ``(x, y, z)``)."""
    out = np.zeros((3, _SPAN + 1), np.int64)
    for axis in range(3):
        for o in range(_SPAN + 1):
            bits = 0
            for x in range(_SPAN):
                for y in range(_SPAN):
                    for z in range(_SPAN):
                        if (x, y, z)[axis] >= _SPAN - o:
                            bits |= 1 << (16 * x + 4 * y + z)
            out[axis, o] = np.uint64(bits).view(np.int64)
    return out


_OVERFLOW = _overflow_masks()


@njit(cache=True, inline="always")
def _box_mask(nx, ny, nz):
    """The mask of the tiles ``[0, nx) x [0, ny) x [0, nz)`` (each 1 to ``_SPAN``): the
    product of one mask per axis, whose set bits (16 x, 4 y, z) add without carries.
    No loop, so that loops calling it vectorise."""
    one = np.int64(1)
    mx = one | (np.int64(nx > 1) << 16) | (np.int64(nx > 2) << 32) | (np.int64(nx > 3) << 48)
    my = one | (np.int64(ny > 1) << 4) | (np.int64(ny > 2) << 8) | (np.int64(ny > 3) << 12)
    mz = (one << nz) - one
    return mx * my * mz


@njit(cache=True, inline="always")
def _merge(children, n, out):
    """Merge nodes ``children[:n]`` of the allocation pyramid into ``out``.

    A node is ``(lo_x, lo_y, lo_z, mask)``: ``mask`` has bit ``16 x + 4 y + z`` set when the
    band touches tile ``lo + (x, y, z)`` (0: no band); ``lo_x == _BIG_LO`` when the band
    spans more than ``_SPAN`` tiles on some axis (then so does the merged node)."""
    # the usual case first: every child has band, none is big, all from the same corner
    # tile; the merge is then the union of the masks
    same = n > 0
    mask = np.int64(0)
    for k in range(n):
        same = same and (
            children[k, 3] != 0
            and children[k, 0] != _BIG_LO
            and children[k, 0] == children[0, 0]
            and children[k, 1] == children[0, 1]
            and children[k, 2] == children[0, 2]
        )
        mask |= children[k, 3]
    if same:
        out[0] = children[0, 0]
        out[1] = children[0, 1]
        out[2] = children[0, 2]
        out[3] = mask
        return
    none = np.iinfo(np.int64).max
    lo0 = none
    lo1 = none
    lo2 = none
    big = False
    for k in range(n):
        if children[k, 0] == _BIG_LO:
            big = True
        elif children[k, 3] != 0:
            lo0 = min(lo0, children[k, 0])
            lo1 = min(lo1, children[k, 1])
            lo2 = min(lo2, children[k, 2])
    mask = np.int64(0)
    if not big and lo0 != none:
        for k in range(n):
            m = children[k, 3]
            if m == 0:
                continue
            ox = children[k, 0] - lo0
            oy = children[k, 1] - lo1
            oz = children[k, 2] - lo2
            if (
                ox > _SPAN
                or oy > _SPAN
                or oz > _SPAN
                or m & _OVERFLOW[0, ox]
                or m & _OVERFLOW[1, oy]
                or m & _OVERFLOW[2, oz]
            ):
                big = True
            else:
                mask |= m << (16 * ox + 4 * oy + oz)
    out[0] = _BIG_LO if big else lo0
    out[1] = lo1
    out[2] = lo2
    out[3] = -1 if big else mask


@njit(cache=True, inline="always")
def _usual_merge(x0, y0, z0, m0, x1, y1, z1, m1, x2, y2, z2, m2, x3, y3, z3, m3):
    """:func:`_merge`'s usual case, without branches (loops calling it vectorise): four
    children ``(lo_x, lo_y, lo_z, mask)`` with band, none big, all from the same corner
    tile. Returns whether that holds, and the union of their masks (then the merged
    node's mask, its corner that of the first child)."""
    same = (
        (m0 != 0) & (m1 != 0) & (m2 != 0) & (m3 != 0) & (x0 != _BIG_LO)
        & (x1 == x0) & (x2 == x0) & (x3 == x0)
        & (y1 == y0) & (y2 == y0) & (y3 == y0)
        & (z1 == z0) & (z2 == z0) & (z3 == z0)
    )  # fmt: skip
    return same, m0 | m1 | m2 | m3


@njit(cache=True, parallel=True)
def _merge_levels(nodes, levels):
    """The levels above level 0 of the node pyramid of :func:`tiles_touched`, each from the
    one below (see :func:`_merge`): a node covers 2 x 2 nodes (layout:
    ``_sampling.pyramid_levels``). One call for all levels: a call per level cost more
    than the levels above the first."""
    for level in range(1, levels.shape[0]):
        src, ch, cw = levels[level - 1]
        dst, ph, pw = levels[level]
        for i in prange(ph):
            children = np.empty((4, 4), np.int64)
            a = nodes[src + 2 * i * cw : src + (2 * i + 1) * cw]
            b = nodes[src + (2 * i + 1) * cw : src + (2 * i + 2) * cw]
            pairs = cw // 2 if 2 * i + 1 < ch else 0
            for j in range(pw):
                out = nodes[dst + i * pw + j]
                if j < pairs:  # the usual case first
                    p = a[2 * j]
                    q = a[2 * j + 1]
                    r = b[2 * j]
                    w = b[2 * j + 1]
                    same, union = _usual_merge(
                        p[0], p[1], p[2], p[3], q[0], q[1], q[2], q[3],
                        r[0], r[1], r[2], r[3], w[0], w[1], w[2], w[3],
                    )  # fmt: skip
                    if same:
                        out[0] = p[0]
                        out[1] = p[1]
                        out[2] = p[2]
                        out[3] = union
                        continue
                n = 0
                for di in range(2):
                    for dj in range(2):
                        if 2 * i + di < ch and 2 * j + dj < cw:
                            children[n] = nodes[src + (2 * i + di) * cw + 2 * j + dj]
                            n += 1
                _merge(children, n, out)


@njit(cache=True, inline="always")
def _emit_mask(node, keys, count, seen):
    for bit in range(64):
        if node[3] & (np.int64(1) << bit):
            a = node[0] + (bit >> 4)
            b = node[1] + ((bit >> 2) & 3)
            c = node[2] + (bit & 3)
            count = _emit_key(a, b, c, keys, count, seen)
    return count


@njit(cache=True, inline="always")
def _min4(a, b, c, d):
    return min(min(a, b), min(c, d))


@njit(cache=True, inline="always")
def _max4(a, b, c, d):
    return max(max(a, b), max(c, d))


@njit(cache=True, inline="always")
def _world(kind, R, t, params, table, u, v, d, out, row):
    x, y, z = _k.unproject_point(kind, params, table, u, v, d)
    for a in range(3):
        out[row, a] = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z + t[a]


@njit(cache=True, inline="always")
def _quad_node(ok, i0, j0, k0, i1, j1, k1):
    """The node (see _merge) ``(lo_x, lo_y, lo_z, mask)`` of a quad whose band-end points lie
    in the tiles ``[i0, i1] x [j0, j1] x [k0, k1]``: big (``_BIG_LO``, mask -1) when that
    spans more than ``_SPAN`` tiles on an axis (quad_tiles covers it); mask 0 when the quad
    is not ``ok`` (valid, see quad_valid). No branch and scalar arguments, so that the loop
    over a row of quads vectorises."""
    ni = i1 - i0 + 1
    nj = j1 - j0 + 1
    nk = k1 - k0 + 1
    big = (ni > _SPAN) | (nj > _SPAN) | (nk > _SPAN)
    mask = _box_mask(min(ni, _SPAN), min(nj, _SPAN), min(nk, _SPAN))
    lo_x = np.int64(_BIG_LO) if big else np.int64(i0)
    mask = np.int64(-1) if big else mask
    return (
        lo_x if ok else np.int64(0),
        np.int64(j0),
        np.int64(k0),
        mask if ok else np.int64(0),
    )


@njit(cache=True, inline="always")
def _quad_box(rng, ranges, qu, qu1, qv, max_disc):
    """:func:`_quad_node` of quad ``(qu, qv)`` whose right-hand column is ``qu1``; ``ranges``
    holds the tiles of every pixel's band-end points (see pixel_ranges)."""
    a = ranges[:, qv]
    b = ranges[:, qv + 1]
    return _quad_node(
        corner_ranges(rng, qu, qu1, qv, max_disc)[4],
        _min4(a[0, qu], a[0, qu1], b[0, qu], b[0, qu1]),
        _min4(a[1, qu], a[1, qu1], b[1, qu], b[1, qu1]),
        _min4(a[2, qu], a[2, qu1], b[2, qu], b[2, qu1]),
        _max4(a[3, qu], a[3, qu1], b[3, qu], b[3, qu1]),
        _max4(a[4, qu], a[4, qu1], b[4, qu], b[4, qu1]),
        _max4(a[5, qu], a[5, qu1], b[5, qu], b[5, qu1]),
    )


@njit(cache=True)
def _node_points(
    kind, rng, qu, qv, a0, a1, b0, b1, params, table, R, t, eps0, eps1, falloff, margin, corners,
    points,
):  # fmt: skip
    # Band-end points of the corners of the sub-quad [a0, a1] x [b0, b1] of quad
    # (qu, qv): rows 0..3 at the near end, 4..7 at the far end; row k has du = k & 1,
    # dv = k >> 1 (only with ``points``). Returns the band's range interval over the
    # sub-quad: both ends are monotone in the bilinear range, so they are extreme at corners.
    qu1 = qu + 1 if qu + 1 < rng.shape[1] else 0
    r00 = rng[qv, qu]
    r01 = rng[qv, qu1]
    r10 = rng[qv + 1, qu]
    r11 = rng[qv + 1, qu1]
    lo = np.inf
    hi = -np.inf
    for k in range(4):
        fu = a1 if k & 1 else a0
        fv = b1 if k >> 1 else b0
        r = (1.0 - fv) * ((1.0 - fu) * r00 + fu * r01) + fv * ((1.0 - fu) * r10 + fu * r11)
        eps = eps0 + eps1 * r
        f = falloff if falloff > 0.0 else eps
        near = max(r - eps - margin, 0.0)
        far = r + eps + f
        lo = min(lo, near)
        hi = max(hi, far)
        if points:
            _world(kind, R, t, params, table, qu + fu, qv + fv, near, corners, k)
            _world(kind, R, t, params, table, qu + fu, qv + fv, far, corners, 4 + k)
    return lo, hi


@njit(cache=True, inline="always")
def _extremes(corners, first):
    # per axis, the least and the greatest coordinate of the four points corners[first:+4]
    c = corners[first : first + 4]
    return (
        _min4(c[0, 0], c[1, 0], c[2, 0], c[3, 0]),
        _min4(c[0, 1], c[1, 1], c[2, 1], c[3, 1]),
        _min4(c[0, 2], c[1, 2], c[2, 2], c[3, 2]),
        _max4(c[0, 0], c[1, 0], c[2, 0], c[3, 0]),
        _max4(c[0, 1], c[1, 1], c[2, 1], c[3, 1]),
        _max4(c[0, 2], c[1, 2], c[2, 2], c[3, 2]),
    )


@njit(cache=True)
def _slab_tiles(
    kind, qu, qv, a0, a1, b0, b1, lo, hi, params, table, R, t, h, T, keys, count, seen,
    corners, box,
):  # fmt: skip
    # Cover a narrow piece of the band (its sub-quad is at most half a tile across) that
    # is long in range: cut the frustum of the sub-quad between ranges lo and hi into
    # slabs about half a tile long, and emit the tiles of each slab's box. A pixel's points
    # are affine in range in every sensor model (tests/test_sensors.py checks it), so a
    # slab's far corners are stepped from the two ends (rows 8..11: the near ends, 12..15:
    # near to far) instead of unprojected: the same points but for rounding, far below
    # the tile tests' slack. Rows 4..7 hold the far ends already (_quad_tiles).
    for k in range(4):
        fu = a1 if k & 1 else a0
        fv = b1 if k >> 1 else b0
        _world(kind, R, t, params, table, qu + fu, qv + fv, lo, corners, k)
    length = 0.0
    for k in range(4):
        d2 = 0.0
        for ax in range(3):
            corners[8 + k, ax] = corners[k, ax]
            corners[12 + k, ax] = corners[4 + k, ax] - corners[k, ax]
            d2 += corners[12 + k, ax] ** 2
        length = max(length, math.sqrt(d2))
    n = min(max(int(math.ceil(length / (0.5 * T * h))), 1), _MAX_SLABS)
    last = (_BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO)
    # a slab's box from the extremes of its two ends, each end's computed once
    near = _extremes(corners, 0)
    for s in range(1, n + 1):
        f = s / n
        for k in range(4):
            for ax in range(3):
                corners[4 + k, ax] = corners[8 + k, ax] + f * corners[12 + k, ax]
        far = _extremes(corners, 4)
        _box_of_ends(near, far, box)
        span = _tile_range(box, h, T)
        if span != last:  # consecutive slabs often cover the same tiles
            count = _emit(span, keys, count, seen)
            last = span
        near = far
    return count


@njit(cache=True)
def _quad_tiles(
    kind, rng, qu, qv, params, table, R, t, eps0, eps1, falloff, margin, h, T, keys, count, seen,
    corners, box, stack,
):  # fmt: skip
    # Cover the band of one valid quad whose box spans more than _SPAN tiles on an axis
    # with boxes spanning at most two:
    # halve the quad across its wider side while the piece is wider than half a tile,
    # then cover each narrow piece by slabs of its range interval (the band across a
    # depth step, or seen edge-on, is long and thin).
    stack[0, 0] = 0.0
    stack[0, 1] = 1.0
    stack[0, 2] = 0.0
    stack[0, 3] = 1.0
    top = 1
    span = (_BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO, _BIG_LO)
    root = True
    while top > 0:
        top -= 1
        a0 = stack[top, 0]
        a1 = stack[top, 1]
        b0 = stack[top, 2]
        b1 = stack[top, 3]
        # the whole quad spans more than _SPAN tiles (the same points as its node's box):
        # its range interval is all it needs of them
        lo, hi = _node_points(
            kind, rng, qu, qv, a0, a1, b0, b1, params, table, R, t, eps0, eps1, falloff, margin,
            corners, not root,
        )  # fmt: skip
        if not root:
            _box_of(corners, box)
            span = _tile_range(box, h, T)
            if span[3] - span[0] <= 1 and span[4] - span[1] <= 1 and span[5] - span[2] <= 1:
                count = _emit(span, keys, count, seen)
                continue
        root = False
        # the piece's width across its frustum at the far end of its range interval, from
        # the far corners that _slab_tiles needs too
        for k in range(4):
            fu = a1 if k & 1 else a0
            fv = b1 if k >> 1 else b0
            _world(kind, R, t, params, table, qu + fu, qv + fv, hi, corners, 4 + k)
        wide_u = 0.0
        wide_v = 0.0
        for ax in range(3):
            wide_u += (corners[5, ax] - corners[4, ax]) ** 2
            wide_v += (corners[6, ax] - corners[4, ax]) ** 2
        if max(wide_u, wide_v) <= (0.5 * T * h) ** 2:
            count = _slab_tiles(
                kind, qu, qv, a0, a1, b0, b1, lo, hi, params, table, R, t, h, T, keys, count,
                seen, corners, box,
            )  # fmt: skip
            continue
        if a1 - a0 < _MIN_PIECE or b1 - b0 < _MIN_PIECE or top + 2 > stack.shape[0]:
            count = _emit(span, keys, count, seen)
            continue
        for half in range(2):
            stack[top, 0] = a0
            stack[top, 1] = a1
            stack[top, 2] = b0
            stack[top, 3] = b1
            if wide_u >= wide_v:
                mid = 0.5 * (a0 + a1)
                stack[top, 0] = a0 if half == 0 else mid
                stack[top, 1] = mid if half == 0 else a1
            else:
                mid = 0.5 * (b0 + b1)
                stack[top, 2] = b0 if half == 0 else mid
                stack[top, 3] = mid if half == 0 else b1
            top += 1
    return count


@functools.cache
def _band_kernels(kind: int):
    """Band-allocation kernels compiled for one sensor kind (see :func:`tiles_touched`)."""

    @njit(cache=True, parallel=True, error_model="numpy")
    def pixel_ranges(rng, params, table, R, t, eps0, eps1, falloff, margin, h, T, out):
        # tiles (lo_x, lo_y, lo_z, hi_x, hi_y, hi_z) of the box of the two band-end points of
        # every pixel, out (6, H, W); a quad's box is the union of its corners' boxes. No
        # branch, so that the loop vectorises: an invalid pixel (NaN) gets meaningless
        # values, and _quad_box uses only the corners of valid quads.
        H, W = rng.shape
        for v in prange(H):
            fv = float(v)
            for u in range(W):
                r = rng[v, u]
                eps = eps0 + eps1 * r
                f = falloff if falloff > 0.0 else eps
                fu = float(u)
                x0, y0, z0 = _k.unproject_point(
                    kind, params, table, fu, fv, max(r - eps - margin, 0.0)
                )
                x1, y1, z1 = _k.unproject_point(kind, params, table, fu, fv, r + eps + f)
                for ax in range(3):
                    e0 = R[ax, 0] * x0 + R[ax, 1] * y0 + R[ax, 2] * z0 + t[ax]
                    e1 = R[ax, 0] * x1 + R[ax, 1] * y1 + R[ax, 2] * z1 + t[ax]
                    out[ax, v, u] = _first_tile(min(e0, e1), h, T)
                    out[3 + ax, v, u] = _last_tile(max(e0, e1), h, T)

    @njit(cache=True, parallel=True, error_model="numpy")
    def quad_nodes(rng, ranges, params, max_disc, nodes):
        # level 0 of the node pyramid: one node per 2 x 2 quads, the merge of theirs
        nqv = rng.shape[0] - 1
        nqu = quad_columns(kind, params)
        W = rng.shape[1]
        cols = -(-nqu // 2)
        for bv in prange(-(-nqv // 2)):
            quads = np.empty((4, 2, nqu), np.int64)  # lo_x, lo_y, lo_z, mask per quad
            children = np.empty((4, 4), np.int64)
            union = np.empty(cols, np.int64)
            same = np.empty(cols, np.bool_)
            rows = min(2, nqv - 2 * bv)
            for r in range(rows):
                qv = 2 * bv + r
                # one view per row: a loop whose inlined helpers take arrays, or that
                # indexes several dimensions, does not vectorise (about 4x slower)
                a = rng[qv]
                b = rng[qv + 1]
                i0a, i0b = ranges[0, qv], ranges[0, qv + 1]
                j0a, j0b = ranges[1, qv], ranges[1, qv + 1]
                k0a, k0b = ranges[2, qv], ranges[2, qv + 1]
                i1a, i1b = ranges[3, qv], ranges[3, qv + 1]
                j1a, j1b = ranges[4, qv], ranges[4, qv + 1]
                k1a, k1b = ranges[5, qv], ranges[5, qv + 1]
                x0, y0, z0, m0 = quads[0, r], quads[1, r], quads[2, r], quads[3, r]
                for qu in range(min(nqu, W - 1)):
                    u1 = qu + 1
                    x0[qu], y0[qu], z0[qu], m0[qu] = _quad_node(
                        quad_valid(a[qu], a[u1], b[qu], b[u1], max_disc),
                        _min4(i0a[qu], i0a[u1], i0b[qu], i0b[u1]),
                        _min4(j0a[qu], j0a[u1], j0b[qu], j0b[u1]),
                        _min4(k0a[qu], k0a[u1], k0b[qu], k0b[u1]),
                        _max4(i1a[qu], i1a[u1], i1b[qu], i1b[u1]),
                        _max4(j1a[qu], j1a[u1], j1b[qu], j1b[u1]),
                        _max4(k1a[qu], k1a[u1], k1b[qu], k1b[u1]),
                    )
                if nqu == W:  # a wrapping sensor's quad between the last column and the first
                    box = _quad_box(rng, ranges, W - 1, 0, qv, max_disc)
                    for f in range(4):
                        quads[f, r, W - 1] = box[f]
            # _merge's usual case first (_usual_merge, vectorised): 2 x 2 valid quads, none
            # big, their boxes from the same corner tile; the node's mask is the union
            pairs = nqu // 2 if rows == 2 else 0
            xa, ya, za, ma = quads[0, 0], quads[1, 0], quads[2, 0], quads[3, 0]
            xb, yb, zb, mb = quads[0, 1], quads[1, 1], quads[2, 1], quads[3, 1]
            for bu in range(pairs):
                c0 = 2 * bu
                c1 = c0 + 1
                same[bu], union[bu] = _usual_merge(
                    xa[c0], ya[c0], za[c0], ma[c0], xa[c1], ya[c1], za[c1], ma[c1],
                    xb[c0], yb[c0], zb[c0], mb[c0], xb[c1], yb[c1], zb[c1], mb[c1],
                )  # fmt: skip
            for bu in range(cols):
                out = nodes[bv * cols + bu]
                if bu < pairs and same[bu]:
                    out[0] = xa[2 * bu]
                    out[1] = ya[2 * bu]
                    out[2] = za[2 * bu]
                    out[3] = union[bu]
                    continue
                n = 0
                for r in range(rows):
                    for qu in range(2 * bu, min(2 * bu + 2, nqu)):
                        for f in range(4):
                            children[n, f] = quads[f, r, qu]
                        n += 1
                _merge(children, n, out)

    @njit(cache=True, parallel=True)
    def band_tiles(
        rng, ranges, params, table, R, t, eps0, eps1, falloff, max_disc, margin, h, T, nodes,
        levels, todo, starts, ends, keys, counts,
    ):  # fmt: skip
        # Walk the node pyramid from each top node ``todo[m]``: a masked node emits its
        # tiles, a big one is opened (a big quad is covered by quad_tiles). The top node's
        # keys go to keys[starts[m]:ends[m]] as far as they fit; counts[todo[m]] receives
        # how many it emits (it did not fit when that exceeds ends[m] - starts[m]).
        top = levels.shape[0] - 1
        tw = levels[top, 2]
        nqv = rng.shape[0] - 1
        nqu = quad_columns(kind, params)
        for m in prange(todo.shape[0]):
            n = todo[m]
            out = keys[starts[m] : ends[m]]
            count = 0
            seen = np.full((_SEEN, 3), np.iinfo(np.int64).min, np.int64)
            corners = np.empty((16, 3))  # see _slab_tiles
            box = np.empty(6)
            quad_stack = np.empty((_STACK, 4))
            quad = np.empty(4, np.int64)
            stack = np.empty((4 * top + 4, 3), np.int64)
            stack[0, 0] = top
            stack[0, 1] = n // tw
            stack[0, 2] = n % tw
            depth = 1
            while depth > 0:
                depth -= 1
                lvl = stack[depth, 0]
                i = stack[depth, 1]
                j = stack[depth, 2]
                node = nodes[levels[lvl, 0] + i * levels[lvl, 2] + j]
                if node[3] == 0:
                    continue
                if node[0] != _BIG_LO:
                    count = _emit_mask(node, out, count, seen)
                elif lvl == 0:  # its 2 x 2 quads, one by one
                    for qv in range(2 * i, min(2 * i + 2, nqv)):
                        for qu in range(2 * j, min(2 * j + 2, nqu)):
                            qu1 = qu + 1 if qu + 1 < rng.shape[1] else 0
                            quad[0], quad[1], quad[2], quad[3] = _quad_box(
                                rng, ranges, qu, qu1, qv, max_disc
                            )
                            if quad[3] == 0:
                                continue
                            if quad[0] != _BIG_LO:
                                count = _emit_mask(quad, out, count, seen)
                                continue
                            count = _quad_tiles(
                                kind, rng, qu, qv, params, table, R, t, eps0, eps1, falloff, margin,
                                h, T, out, count, seen, corners, box, quad_stack,
                            )  # fmt: skip
                else:
                    for di in range(2):
                        for dj in range(2):
                            ci = 2 * i + di
                            cj = 2 * j + dj
                            if ci < levels[lvl - 1, 1] and cj < levels[lvl - 1, 2]:
                                stack[depth, 0] = lvl - 1
                                stack[depth, 1] = ci
                                stack[depth, 2] = cj
                                depth += 1
            counts[n] = count

    return pixel_ranges, quad_nodes, band_tiles


def _band_tile_keys(scan: PreparedScan, grid: GridSpec, scratch: Scratch | None) -> np.ndarray:
    h = grid.voxel_size
    T = grid.tile_size
    margin = BAND_MARGIN_VOX * h
    R = np.ascontiguousarray(scan.T_W_S[:3, :3])
    t = np.ascontiguousarray(scan.T_W_S[:3, 3])
    rng = scan.surface_m
    pixel_ranges, quad_nodes, band_tiles = _band_kernels(scan.kind)
    ranges = scratch_array(scratch, "pixel_ranges", (6, *rng.shape), np.int32)
    pixel_ranges(
        rng, scan.params, scan.table, R, t, scan.eps, scan.eps_per_m, scan.falloff, margin, h, T,
        ranges,
    )  # fmt: skip
    # the node pyramid: nodes of 2 x 2 quads, then 2 x 2 merges up to _TOP_NODES nodes
    nqu = int(quad_columns(scan.kind, scan.params))
    levels = pyramid_levels(-(-(rng.shape[0] - 1) // 2), -(-nqu // 2), _TOP_NODES)
    n_nodes = int(levels[-1, 0] + levels[-1, 1] * levels[-1, 2])
    nodes = scratch_array(scratch, "nodes", (n_nodes, 4), np.int64)
    quad_nodes(rng, ranges, scan.params, scan.max_discontinuity, nodes)
    _merge_levels(nodes, levels)
    args = (
        rng, ranges, scan.params, scan.table, R, t, scan.eps, scan.eps_per_m, scan.falloff,
        scan.max_discontinuity, margin, h, T, nodes, levels,
    )  # fmt: skip
    # one walk with room for _WALK_ROOM keys per top node; the rare top node that emits
    # more (a LiDAR's far rings) walks again into room of its exact size
    n_top = int(levels[-1, 1] * levels[-1, 2])
    todo = np.arange(n_top, dtype=np.int64)
    starts = todo * _WALK_ROOM
    counts = np.zeros(n_top, np.int64)
    keys = scratch_array(scratch, "walk_keys", (n_top * _WALK_ROOM, 3), np.int64)
    band_tiles(*args, todo, starts, starts + _WALK_ROOM, keys, counts)
    again = todo[counts > _WALK_ROOM]
    more = np.zeros((0, 3), np.int64)
    if len(again):
        ends = np.cumsum(counts[again])
        more = np.empty((int(ends[-1]), 3), np.int64)
        band_tiles(*args, again, ends - counts[again], ends, more, counts)
    return unique_keys(_walk_keys(keys, counts, _WALK_ROOM, more))


@njit(cache=True)
def _walk_keys(keys, counts, room, more):
    # The walk's keys in one array: top node n's are keys[n * room : n * room + counts[n]]
    # when they fit, else in ``more`` (a boolean mask over the whole room cost 0.3 ms per
    # scan)
    total = more.shape[0]
    for n in range(counts.shape[0]):
        if counts[n] <= room:
            total += counts[n]
    out = np.empty((total, 3), np.int64)
    k = 0
    for n in range(counts.shape[0]):
        if counts[n] <= room:
            out[k : k + counts[n]] = keys[n * room : n * room + counts[n]]
            k += counts[n]
    out[k:] = more
    return out


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


def tiles_touched(scan: PreparedScan, grid: GridSpec, scratch: Scratch | None = None) -> np.ndarray:
    """Keys (int64 (n, 3), sorted, unique) of the tiles this scan allocates.

    Mapping mode: tiles near the measured surface (the band ``[-eps - margin, eps + falloff]``
    around every valid pixel quad; with bounds, only tiles of the region of interest).
    Closed mode: tiles of the region of interest in view of the scan. ``scratch`` lends the
    working arrays (see :mod:`engine._memory`).
    """
    if grid.mode == "closed":
        if not math.isfinite(scan.reach_max):
            return np.zeros((0, 3), np.int64)
        return _roi_tiles_in_view(scan, grid)
    # no pyramid needed: a scan without a valid quad has no band
    keys = _band_tile_keys(scan, grid, scratch)
    if grid.bounds is not None:
        keys = keys[_inside_roi(grid, keys)]
    return keys
