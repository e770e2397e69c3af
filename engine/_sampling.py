"""Range-map sampling inside kernels (METHOD.md §1, "Exact conventions").

The interpolated range at ``(u, v)`` is bilinear over the four pixels of the quad
around the point (:func:`bilinear`), and the point gets information only when all
four are valid, optionally within ``max_disc`` metres of each other
(:func:`corner_ranges`). :func:`sample_range` puts the two together for one point
(edge refinement, through :func:`point_contribution`); the fusion kernel reads
the same quad validity from :func:`quad_bounds` (an invalid quad reaches
nothing) and then calls :func:`bilinear`; the tile tests read the bounds'
pyramid. One definition, three ways in.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from . import _sensor_kernels as _k
from ._memory import Scratch, scratch_array
from ._sensor_kernels import P_H, P_W, in_image, wraps
from .certainty import contribution

#: Quads per side of a block of the finest level of the statistics the tile tests read.
QUAD_BLOCK = 4
#: A pixel rectangle is tested against the finest level of the block pyramid at which it
#: covers fewer than this many nodes per side (see :func:`bounds_and_pyramid`).
PYRAMID_SPAN = 4


@njit(cache=True, inline="always")
def quad_columns(kind, params):
    """Number of pixel quads along a row: W for a wrapping sensor, else W - 1."""
    W = int(params[P_W])
    return W if wraps(kind, params) else W - 1


@njit(cache=True, inline="always")
def quad_origin(kind, params, u, v):
    """Quad ``(qu, qv)`` that holds pixel coordinates already known to be in the image."""
    W = int(params[P_W])
    H = int(params[P_H])
    qu = int(math.floor(u))
    qv = int(math.floor(v))
    if qv > H - 2:
        qv = H - 2
    if not wraps(kind, params) and qu > W - 2:
        qu = W - 2
    return qu, qv


@njit(cache=True, inline="always")
def quad_index(kind, params, u, v):
    """Flat index ``qv * quad_columns + qu`` of the quad that holds ``(u, v)``, or -1 when
    ``(u, v)`` is not in the image (NaN included): :func:`in_image` and :func:`quad_origin`
    in one, written without branches so that loops calling it vectorise."""
    W = params[P_W]
    H = params[P_H]
    if wraps(kind, params):
        inside = (v >= 0.0) & (v <= H - 1.0) & (u >= 0.0) & (u < W)
        u_cap = W - 1.0
    else:
        inside = (v >= 0.0) & (v <= H - 1.0) & (u >= 0.0) & (u <= W - 1.0)
        u_cap = W - 2.0
    # truncation is floor here: both are clamped to be >= 0
    qu = np.int64(min(max(u, 0.0), u_cap))
    qv = np.int64(min(max(v, 0.0), H - 2.0))
    return qv * quad_columns(kind, params) + qu if inside else np.int64(-1)


@njit(cache=True, inline="always")
def column_ranges(rng, qu, qv, u):
    """The ranges at column ``u`` on the two rows of quad ``(qu, qv)`` (columns wrap):
    linear along each row; :func:`bilinear` is linear between them."""
    qu1 = qu + 1
    if qu1 == rng.shape[1]:
        qu1 = 0
    fu = u - qu
    top = (1.0 - fu) * rng[qv, qu] + fu * rng[qv, qu1]
    bottom = (1.0 - fu) * rng[qv + 1, qu] + fu * rng[qv + 1, qu1]
    return top, bottom


@njit(cache=True, inline="always")
def bilinear(rng, qu, qv, u, v):
    """Bilinear range at ``(u, v)`` in quad ``(qu, qv)`` (columns wrap), the quad known to
    be valid."""
    top, bottom = column_ranges(rng, qu, qv, u)
    fv = v - qv
    return (1.0 - fv) * top + fv * bottom


@intrinsic
def prefetch(typingctx, array, i, j):
    """Start loading the cache line that holds ``array[i, j]`` (a 2-D array; the indices in
    bounds) and go on: LLVM's ``prefetch`` intrinsic, for reading, into every cache level
    (``prefetcht0`` on x86). It never faults and changes no value."""
    sig = types.void(array, i, j)

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        ary = context.make_array(array_type)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(
            context, builder, array_type, ary, [args[1], args[2]], wraparound=False
        )
        i32 = ir.IntType(32)
        byte_ptr = ir.IntType(8).as_pointer()  # one declaration whatever the array's dtype
        fnty = ir.FunctionType(ir.VoidType(), [byte_ptr, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        read, all_levels, data_cache = (ir.Constant(i32, flag) for flag in (0, 3, 1))
        builder.call(fn, [builder.bitcast(ptr, byte_ptr), read, all_levels, data_cache])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always")
def prefetch_quad(kind, params, rng, u, v):
    """Start loading the two rows of the quad around ``(u, v)`` (in the image) that
    :func:`bilinear` will read: the fusion kernel queues its band points in one pass and
    interpolates them in the next, and the range map's lines missing from cache cost that
    pass half its time (0.4 of 0.7 ms per 2 cm room frame)."""
    qu, qv = quad_origin(kind, params, u, v)
    prefetch(rng, qv, qu)
    prefetch(rng, qv + 1, qu)


@njit(cache=True, inline="always")
def sample_range(kind, params, rng, u, v, max_disc):
    """Bilinear range at ``(u, v)`` and whether the point gets information.

    ``rng`` is a prepared range map: finite values and NaN (no-return pixels already
    converted). ``max_disc < 0`` disables the depth-discontinuity test.
    """
    if not in_image(kind, params, u, v):
        return math.nan, False
    qu, qv = quad_origin(kind, params, u, v)
    if not quad_ranges(rng, qu, qv, max_disc)[4]:
        return math.nan, False
    return bilinear(rng, qu, qv, u, v), True


@njit(cache=True, inline="always")
def quad_valid(r00, r01, r10, r11, max_disc):
    """Whether a quad with these corner ranges informs anything: all four valid and, with
    ``max_disc >= 0``, within ``max_disc`` of each other. No branch, so that loops over quads
    vectorise (scalar arguments: a loop whose inlined helpers take arrays does not)."""
    spread = max(max(r00, r01), max(r10, r11)) - min(min(r00, r01), min(r10, r11))
    ok = (r00 == r00) & (r01 == r01) & (r10 == r10) & (r11 == r11)  # none is NaN
    return ok & ((max_disc < 0.0) | (spread <= max_disc))


@njit(cache=True, inline="always")
def corner_ranges(rng, qu, qu1, qv, max_disc):
    """The four corner ranges of quad ``(qu, qv)`` whose right-hand column is ``qu1``, and
    whether the quad informs anything (:func:`quad_valid`)."""
    r00 = rng[qv, qu]
    r01 = rng[qv, qu1]
    r10 = rng[qv + 1, qu]
    r11 = rng[qv + 1, qu1]
    return r00, r01, r10, r11, quad_valid(r00, r01, r10, r11, max_disc)


@njit(cache=True, inline="always")
def quad_ranges(rng, qu, qv, max_disc):
    """:func:`corner_ranges` of quad ``(qu, qv)``, columns wrapping."""
    qu1 = qu + 1
    if qu1 == rng.shape[1]:
        qu1 = 0
    return corner_ranges(rng, qu, qu1, qv, max_disc)


#: Slack (metres, plus the same relative to the range) by which :func:`quad_bounds` widens its
#: bounds, so that float32 storage and rounding never make them claim a voxel wrongly.
_BOUND_SLACK = 1e-6


def widened(reach: float) -> float:
    """An upper bound on the reach that :func:`quad_bounds` stores for a true ``reach``
    (twice its slack: the float32 rounding after the slack moves it by far less)."""
    return reach + 2.0 * _BOUND_SLACK * (1.0 + abs(reach))


@njit(cache=True, inline="always")
def _bounds_of(r00, r01, r10, r11, eps0, eps1, falloff, max_disc):
    """The two bounds of a quad with these corner ranges (see :func:`quad_bounds`)."""
    ok = quad_valid(r00, r01, r10, r11, max_disc)
    lo = min(min(r00, r01), min(r10, r11))
    hi = max(max(r00, r01), max(r10, r11))
    free = (1.0 - eps1) * lo - eps0  # eps1 < 1: increasing in r
    eps = eps0 + eps1 * hi
    f = falloff if falloff > 0.0 else eps
    behind = hi + eps + f
    return (
        free - _BOUND_SLACK * (1.0 + abs(free)) if ok else -np.inf,
        behind + _BOUND_SLACK * (1.0 + abs(behind)) if ok else -np.inf,
    )


@njit(cache=True, parallel=True, error_model="numpy")
def quad_bounds(kind, params, rng, eps0, eps1, falloff, max_disc, out, free, reach):
    """Per pixel quad, two distances that settle most points without interpolating
    (``out`` float32 (H - 1, quad_columns, 2)):

    * ``out[..., 0]``: below it, a point projecting into the quad is in free space in front
      of the band (``d - r < -eps(r)`` for every range ``r`` between the quad's corners);
    * ``out[..., 1]``: beyond it, the quad informs nothing (``d - r > eps(r) + f(r)``).

    Both ends increase with ``r`` (``0 <= eps1 < 1``), so the extremes are at the smallest
    and the largest corner. An invalid quad informs nothing: ``(-inf, -inf)``. Each bound is moved
    outwards by ``_BOUND_SLACK`` (absolute and relative) so that it errs on the safe side.

    With non-empty ``free`` and ``reach`` (float64, one per block of ``QUAD_BLOCK`` x
    ``QUAD_BLOCK`` quads, row-major), also level 0 of :func:`bounds_and_pyramid`: each
    block's smallest lower and largest upper bound, folded while its rows are in cache (a
    separate pass over the bounds cost more than computing them).

    A row of quads is computed from the two rows of pixels into two contiguous buffers, then
    interleaved: a loop that stores both bounds of a quad side by side does not vectorise
    (3.6x slower).
    """
    nqv = rng.shape[0] - 1
    nqu = quad_columns(kind, params)
    W = rng.shape[1]
    cols = -(-nqu // QUAD_BLOCK)
    blocks = free.shape[0] > 0
    for bv in prange(-(-nqv // QUAD_BLOCK)):
        lower = np.empty(nqu, np.float32)
        upper = np.empty(nqu, np.float32)
        # per column of quads, the extremes over the block's rows (padded to whole blocks)
        padded = cols * QUAD_BLOCK if blocks else 0
        lo = np.full(padded, np.inf, np.float32)
        hi = np.full(padded, -np.inf, np.float32)
        for qv in range(bv * QUAD_BLOCK, min(nqv, (bv + 1) * QUAD_BLOCK)):
            a = rng[qv]
            b = rng[qv + 1]
            for qu in range(min(nqu, W - 1)):  # branch-free: vectorises
                lower[qu], upper[qu] = _bounds_of(
                    a[qu], a[qu + 1], b[qu], b[qu + 1], eps0, eps1, falloff, max_disc
                )
            if nqu == W:  # a wrapping sensor's quad between the last column and the first
                lower[W - 1], upper[W - 1] = _bounds_of(
                    a[W - 1], a[0], b[W - 1], b[0], eps0, eps1, falloff, max_disc
                )
            row = out[qv]
            for qu in range(nqu):
                row[qu, 0] = lower[qu]
                row[qu, 1] = upper[qu]
            if blocks:
                for qu in range(nqu):
                    lo[qu] = min(lo[qu], lower[qu])
                    hi[qu] = max(hi[qu], upper[qu])
        if blocks:
            for bu in range(cols):
                least = np.inf
                most = -np.inf
                for c in range(bu * QUAD_BLOCK, (bu + 1) * QUAD_BLOCK):
                    least = min(least, lo[c])
                    most = max(most, hi[c])
                free[bv * cols + bu] = least
                reach[bv * cols + bu] = most


def _bounds_array(scratch: Scratch | None, kind, params, rng) -> np.ndarray:
    shape = (rng.shape[0] - 1, quad_columns(kind, params), 2)
    return scratch_array(scratch, "quad_bounds", shape, np.float32)


_NO_BLOCKS = np.zeros(0)


def quad_bounds_array(
    kind, params, rng, eps0, eps1, falloff, max_disc, scratch: Scratch | None = None
) -> np.ndarray:
    """:func:`quad_bounds` of a prepared range map, float32 (H - 1, quad_columns, 2) (in
    ``scratch``'s array "quad_bounds" when given)."""
    out = _bounds_array(scratch, kind, params, rng)
    quad_bounds(kind, params, rng, eps0, eps1, falloff, max_disc, out, _NO_BLOCKS, _NO_BLOCKS)
    return out


def bounds_and_pyramid(
    kind, params, rng, eps0, eps1, falloff, max_disc, scratch: Scratch | None = None
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`quad_bounds_array` and the bounds reduced for tile tests: over blocks of
    ``QUAD_BLOCK`` x ``QUAD_BLOCK`` quads (level 0), then over 2 x 2 nodes level by level up
    to one node. The pyramid is flat arrays ``free`` (the smallest free-space bound: a
    point of the node's pixels nearer than it is free space; ``-inf`` where a quad is
    invalid) and ``reach`` (the largest reach: nothing farther is informed), and ``levels``
    (int64 (L, 3): offset, rows, columns of each level).

    Tile tests fold the nodes of the finest level at which a pixel rectangle covers fewer
    than ``PYRAMID_SPAN`` nodes per side: a superset of its blocks, so the test stays
    conservative, at a bounded cost whatever the rectangle's size.
    """
    out = _bounds_array(scratch, kind, params, rng)
    levels = pyramid_levels(-(-out.shape[0] // QUAD_BLOCK), -(-out.shape[1] // QUAD_BLOCK))
    size = int(levels[-1, 0] + levels[-1, 1] * levels[-1, 2])
    free = np.empty(size)
    reach = np.empty(size)
    quad_bounds(kind, params, rng, eps0, eps1, falloff, max_disc, out, free, reach)
    _reduce_levels(free, reach, levels)
    return out, (free, reach, levels)


def pyramid_levels(rows: int, cols: int, top_nodes: int = 1) -> np.ndarray:
    """Layout of a pyramid of nodes stored flat, level after level: level 0 has ``rows`` x
    ``cols`` nodes, each level above covers 2 x 2 nodes of the one below, up to a level of
    at most ``top_nodes`` nodes. Returns int64 (L, 3): offset, rows, columns per level."""
    return _pyramid_levels(int(rows), int(cols), int(top_nodes)).copy()


@functools.lru_cache(maxsize=64)
def _pyramid_levels(rows: int, cols: int, top_nodes: int) -> np.ndarray:
    # one layout per image shape: building it cost 0.1 ms per scan, as much as a kernel
    shapes = [(rows, cols)]
    while shapes[-1][0] * shapes[-1][1] > top_nodes:
        shapes.append((-(-shapes[-1][0] // 2), -(-shapes[-1][1] // 2)))
    sizes = [a * b for a, b in shapes]
    offsets = np.concatenate([[0], np.cumsum(sizes[:-1])]).astype(np.int64)
    return np.array([(o, a, b) for o, (a, b) in zip(offsets, shapes, strict=True)], np.int64)


@njit(cache=True)
def _reduce_levels(free, reach, levels):
    # the pyramid's levels above level 0: each node covers 2 x 2 nodes of the level below
    # (one call: a call per level cost more than its work)
    for level in range(1, levels.shape[0]):
        src, rows, cols = levels[level - 1]
        dst, out_rows, out_cols = levels[level]
        for i in range(out_rows):
            for j in range(out_cols):
                lo = np.inf
                hi = -np.inf
                for di in range(2):
                    for dj in range(2):
                        if 2 * i + di < rows and 2 * j + dj < cols:
                            k = src + (2 * i + di) * cols + 2 * j + dj
                            lo = min(lo, free[k])
                            hi = max(hi, reach[k])
                free[dst + i * out_cols + j] = lo
                reach[dst + i * out_cols + j] = hi


@njit(cache=True, inline="always")
def point_contribution(
    kind, shape, params, table, rng, max_disc, eps0, eps1, rho, falloff, q_rho, px, py, pz
):
    """One scan's quantised ``logit(C)`` at a point of the sensor frame (METHOD §1), and
    whether the point is informed: projection, bilinear range, certainty. Edge refinement
    evaluates its samples through it; the fusion kernel runs the same steps in passes over a
    tile (``engine.fusion``), through the same :func:`quad_index`/:func:`quad_origin`,
    :func:`bilinear` and ``contribution``."""
    u, v, d = _k.project_point(kind, params, table, px, py, pz)
    if u != u:
        return np.int64(0), False
    r, ok = sample_range(kind, params, rng, u, v, max_disc)
    if not ok:
        return np.int64(0), False
    return contribution(d - r, r, eps0, eps1, rho, falloff, shape, q_rho)
