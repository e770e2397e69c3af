"""Which tiles a scan allocates (DESIGN.md invariant 1): :func:`tiles_touched`.

Mapping mode: the tiles that the band ``[-eps - margin, eps + falloff]`` around the measured
surface touches: the tiles of the box of each valid pixel quad's band-end points. A pyramid
of nodes (2 x 2 quads per level up) keeps, per node, a 4 x 4 x 4 tile mask of what its quads
touch (:mod:`engine._alloc_masks`), so a walk from the top emits each region's tiles once
instead of once per quad. A quad whose box spans more than four tiles on an axis (the band
across a depth step, or seen edge-on) is covered by pieces: halved while wider than half a
tile, then cut into slabs of its range interval. No-return pixels carve free space but have
no surface, so their quads allocate nothing. Closed mode: the tiles of the region of
interest that are in view (:func:`engine.classify.tiles_in_view`).

The set is a function of the scan alone, so the volume does not depend on the order in
which scans arrive. Kernels are compiled per sensor kind (the kind is a closure constant),
so the branches of the other models cost nothing. Tile keys are int64 (n, 3).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from . import _sensor_kernels as _k
from ._alloc_masks import (
    _BIG_LO,
    _SEEN,
    _SPAN,
    _box_mask,
    _box_of,
    _box_of_ends,
    _emit,
    _emit_mask,
    _extremes,
    _first_tile,
    _last_tile,
    _max4,
    _merge,
    _merge_levels,
    _min4,
    _tile_range,
    _usual_merge,
)
from ._memory import Scratch, scratch_array
from ._sampling import corner_ranges, pyramid_levels, quad_columns, quad_valid
from .classify import reach_radius, tiles_in_view
from .defaults import BAND_MARGIN_VOX
from .grid import GridSpec, unique_keys
from .scans import PreparedScan

__all__ = ["tiles_touched"]

#: Smallest piece of a quad (per side) that allocation subdivides to; it bounds the cost of
#: depth-discontinuity quads (beyond it the covering boxes just grow).
_MIN_PIECE = 1.0 / 64.0
#: Depth of the subdivision stack (two entries per halving).
_STACK = 32
#: Most slabs one narrow piece of a quad's band is cut into (a bound on the work per quad).
_MAX_SLABS = 4096
#: The allocation pyramid is merged up to at most this many top nodes (the parallel walk).
_TOP_NODES = 256
#: Keys each top node's walk can hold (most emit far fewer; see _band_tile_keys).
_WALK_ROOM = 1024


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
# closed mode, and the common entry point


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
