"""Tile masks of mapping-mode allocation (:mod:`engine.allocation`): tile ranges of boxes,
the emission of tile keys through a small cache of recent keys, and the 4 x 4 x 4 tile masks
of the allocation pyramid's nodes with their merges.

A node of the pyramid keeps, for the quads under it, the lowest tile ``(x, y, z)`` of a
4 x 4 x 4 block and a 64-bit mask of the tiles of that block its quads' bands touch; a node
whose band spans more than four tiles on an axis is *big* (``lo_x`` is ``_BIG_LO``) and is
covered quad by quad instead.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__: list[str] = []

#: Tiles per axis of the masks of the allocation pyramid (4 x 4 x 4 tiles: 64 bits).
_SPAN = 4
#: ``lo_x`` of a node of the allocation pyramid whose band spans more than ``_SPAN`` tiles.
_BIG_LO = np.iinfo(np.int64).min
#: Entries of the cache of recently emitted tile keys in allocation (a power of two).
_SEEN = 256
#: Voxels: a band box reaching this close to a voxel centre counts as holding it.
_CENTRE_SLACK = 1e-6


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
