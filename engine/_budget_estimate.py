"""The estimate of :mod:`engine.budget` for mapping mode: how many tiles
:func:`engine.allocation.tiles_touched` will allocate for a scan, in NumPy on a subsample of
its range map (no kernel: nothing is compiled in the API process that calls it), without
enumerating tiles, so that a voxel size a thousand times too small costs what a sensible one
does.

*The sheet.* The range map is cut into blocks of ``s x s`` pixel quads whose corners are
sampled (``s`` such that about :data:`SAMPLES` pixels are). A block whose corners are valid
measurements is a piece of the measured surface with vector area ``a`` (from the four
triangles of its corners; a lone invalid corner leaves the parallelogram of the other
three). The allocation covers, around every valid pixel quad, the axis-aligned box of its
band ``[-eps - margin, eps + falloff]`` along the lines of sight (widened to the next voxel
centre): the sheet swept by a box of extents ``g_k = |c_k| + w_k + h`` (``c`` the band along
the line of sight, ``w`` a pixel quad's own extent, at most half a tile as allocation cuts
larger quads). For a randomly placed lattice of tiles of edge ``T`` the tiles a convex body
meets number ``vol(body + cube) / T^3``, a Minkowski sum whose volume for a zonotope is the
sum of its generators' triple determinants: for a piece of a larger sheet,
``sum_k |a_k| (g_k + T) / T^3``. The sheet's boundary adds its edges' terms (half of
``sum_i |e_i| prod_(j != i) (g_j + T)`` per boundary side) and one corner term; a block
next to one cut by a silhouette counts half of it again.

*Depth steps.* A pixel quad across a depth step (a silhouette against the background, a
spike, a flying pixel) allocates a column of tiles along its line of sight from the near
side to the far side. They are found at full resolution: quads whose ranges spread by more
than half a tile and three times as much as their least-spread neighbour (a surface seen at
a grazing angle spreads about as much in its neighbours). Quads in one bin of about a
tile's width in pixels share their columns (the longest one, as wide as the bin's steps
reach across rows and columns); a line of sight crosses ``sum_k |d_k| (1 + |d_j| / 2)
(1 + |d_l| / 2)`` tiles per tile length in the allocation's boxes of half-tile slabs. A
block that holds a step counts its steps instead of its sheet (across a step, the sheet is
the wall between the two sides, counted once).

No-return and invalid pixels allocate nothing. The estimate does not apply the range filter,
and the sheet counts depth steps that the discontinuity test would drop. Measured against
the real allocation: ``docs/budgets.md``.
"""

from __future__ import annotations

import math

import numpy as np

from . import _sensor_kernels as _k
from .certainty import NoiseModel
from .defaults import BAND_MARGIN_VOX
from .grid import KEY_LIMIT, GridSpec
from .scans import FusionParams, Scan
from .sensors import Sensor

__all__ = ["NO_KEYS", "SAMPLES", "coarser", "mapping_tiles", "rays"]

#: About this many pixels of a scan are sampled (the stride is chosen for it).
SAMPLES = 4096
#: No tile keys.
NO_KEYS = np.zeros(0, np.int64)


def mapping_tiles(
    scan: Scan, params: FusionParams, grid: GridSpec, with_keys: bool
) -> tuple[int, np.ndarray, int, float]:
    """The estimate of a mapping-mode scan's tiles (see the module's note); the packed keys of
    the tiles of its surface points sampled about a tile apart and the level of cells at
    which they are dense (``with_keys``, else none and 0; :func:`coarser`); the farthest
    coordinate of its band's far ends from the origin, metres (when that lies past the tile
    keys' range, nothing else is computed: 0 tiles)."""
    sensor = scan.sensor
    H, W = scan.range_m.shape
    stride = max(1, round(math.sqrt(H * W / SAMPLES)))
    kind, p, _ = sensor.kernel_args()
    rows, v = _samples(H, stride, wrap=False)
    cols, u = _samples(W, stride, wrap=_wraps(kind, p))
    r = scan.range_m[np.ix_(rows, cols)].astype(np.float64)
    r[~np.isfinite(r)] = np.nan  # no return (+inf) has no surface: it allocates nothing
    noise = scan.noise if scan.noise is not None else params.noise
    h = grid.voxel_size
    eps = noise.eps + noise.eps_per_m * r
    falloff = eps if noise.falloff is None else noise.falloff
    near = np.maximum(r - eps - BAND_MARGIN_VOX * h, 0.0)
    far = r + eps + falloff
    A, B = rays(sensor, u[None, :], v[:, None])
    R = scan.T_W_S[:3, :3]
    t = scan.T_W_S[:3, 3]
    A_W = A @ R.T + t
    B_W = B @ R.T
    surface = A_W + r[..., None] * B_W
    band = (far - near)[..., None] * B_W  # the band's extent along each line of sight
    tile_m = grid.tile_size_m
    reach_m = float(np.nanmax(np.abs(A_W + far[..., None] * B_W), initial=0.0))
    if not reach_m / tile_m < KEY_LIMIT - 2:
        return 0, NO_KEYS, 0, reach_m
    keys, level = NO_KEYS, 0
    if with_keys:
        keys, level = _dense_keys(scan, surface, u, stride, tile_m)
    shape = (len(v) - 1, len(u) - 1)  # blocks
    pixels = (
        np.broadcast_to(np.diff(u)[None, :], shape),
        np.broadcast_to(np.diff(v)[:, None], shape),
    )
    blocks, boundary = _sheet_tiles(surface, band, pixels, h, tile_m)
    # depth steps at full resolution; a block that holds one counts them instead of its
    # sheet (which, across a step, is the wall between its two sides)
    steps, stepped = _step_tiles(
        scan, B_W, np.diff(u), noise, BAND_MARGIN_VOX * h, params.max_discontinuity, tile_m,
        (rows[:-1], cols[:-1]),
    )  # fmt: skip
    tiles = math.ceil(float(np.sum(blocks[~stepped])) + boundary + steps)
    return tiles, keys, level, reach_m


def _samples(n: int, stride: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """Sampled pixel indices along one image axis (the last pixel always, so that the blocks
    cover the image) and their coordinates (a wrapping axis ends with column 0 again, at
    coordinate ``n``: the quad between the last column and the first)."""
    index = np.arange(0, n, stride)
    if index[-1] != n - 1:
        index = np.append(index, n - 1)
    coord = index.astype(np.float64)
    if wrap:
        index = np.append(index, 0)
        coord = np.append(coord, float(n))
    return index, coord


def rays(sensor: Sensor, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A``, ``B`` (..., 3) with ``unproject(u, v, d) = A + d B`` in the sensor frame: every
    sensor model is affine in range along a pixel's line of sight (NumPy twin of
    ``_sensor_kernels.unproject_point`` for integer rows; ``tests/test_budgets.py``)."""
    kind, p, table = sensor.kernel_args()
    zero = np.zeros(np.broadcast(u, v).shape)
    u = u + zero
    v = v + zero
    if kind == _k.PINHOLE:
        xn = (u - p[_k.P_CX]) / p[_k.P_FX]
        yn = (v - p[_k.P_CY]) / p[_k.P_FY]
        B = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        if p[_k.P_Z_CONV] == 0.0:
            B /= np.linalg.norm(B, axis=-1, keepdims=True)
        return np.zeros_like(B), B
    if kind == _k.ORTHOGRAPHIC:
        A = np.stack([(u - p[_k.P_OCX]) * p[_k.P_SX], (v - p[_k.P_OCY]) * p[_k.P_SY], zero], -1)
        return A, np.stack([zero, zero, zero + 1.0], axis=-1)
    az = p[_k.P_AZ_MIN] + u * p[_k.P_DAZ]
    if kind == _k.SPHERICAL:
        if p[_k.P_HAS_TABLE] != 0.0:
            el = table[v.astype(np.int64)]
        else:
            el = p[_k.P_EL_MAX] - v * p[_k.P_DEL]
        B = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
        return np.zeros_like(B), B
    # cylindrical
    if p[_k.P_LINEAR] != 0.0:  # radial range only: rho = d, z from the row
        z = (p[_k.P_CYL_CY] - v) / p[_k.P_CYL_FY]
        A = np.stack([zero, zero, z], axis=-1)
        return A, np.stack([np.cos(az), np.sin(az), zero], axis=-1)
    t = (p[_k.P_CYL_CY] - v) / p[_k.P_CYL_FY]
    B = np.stack([np.cos(az), np.sin(az), t], axis=-1)
    if p[_k.P_RADIAL] == 0.0:
        B /= np.sqrt(1.0 + t * t)[..., None]
    return np.zeros_like(B), B


def _wraps(kind: int, p: np.ndarray) -> bool:
    """``_sensor_kernels.wraps`` in Python (calling the kernel would compile it here)."""
    return kind in (_k.SPHERICAL, _k.CYLINDRICAL) and bool(p[_k.P_WRAP] != 0.0)


def _dense_keys(
    scan: Scan, surface: np.ndarray, u: np.ndarray, stride: int, tile_m: float
) -> tuple[np.ndarray, int]:
    """Distinct packed keys of the tiles of surface points sampled about a tile apart (at
    the median spacing of the sampled points along a row, at most every pixel), and the
    level of coarser cells (``2^level`` tiles a side) at which nine in ten of the points
    lie closer together than a cell (:func:`coarser`)."""
    with np.errstate(invalid="ignore"):
        pitch = np.linalg.norm(np.diff(surface, axis=1), axis=-1) / np.diff(u)[None, :]
        finite = pitch[np.isfinite(pitch)]
    if finite.size == 0:
        return NO_KEYS, 0
    spacing, far = np.percentile(finite, [50, 90])
    step = stride if spacing <= 0.0 else int(min(stride, max(1, tile_m // spacing)))
    if step < stride:
        kind, p, _ = scan.sensor.kernel_args()
        H, W = scan.range_m.shape
        rows, v_k = _samples(H, step, wrap=False)
        cols, u_k = _samples(W, step, wrap=_wraps(kind, p))
        r = scan.range_m[np.ix_(rows, cols)].astype(np.float64)
        r[~np.isfinite(r)] = np.nan
        A, B = rays(scan.sensor, u_k[None, :], v_k[:, None])
        surface = (A + r[..., None] * B) @ scan.T_W_S[:3, :3].T + scan.T_W_S[:3, 3]
    level = max(0, math.ceil(math.log2(max(far * step / tile_m, 1.0))))
    return _surface_keys(surface, tile_m), level


def coarser(keys: np.ndarray, level: int) -> np.ndarray:
    """Distinct packed keys of the cells of ``2^level`` tiles a side that hold ``keys``."""
    if level == 0 or keys.size == 0:
        return keys
    mask = (1 << 21) - 1
    axes = [((keys >> shift) & mask) - KEY_LIMIT for shift in (42, 21, 0)]
    a, b, c = (np.floor_divide(x, 1 << level) + KEY_LIMIT for x in axes)
    return np.unique((a << 42) | (b << 21) | c)


def _surface_keys(surface: np.ndarray, tile_m: float) -> np.ndarray:
    """Distinct packed keys of the tiles of the finite points ``surface`` (..., 3)."""
    x = surface.reshape(-1, 3)
    x = x[np.isfinite(x[:, 0])]
    k = np.floor(x / tile_m).astype(np.int64) + KEY_LIMIT
    return np.unique((k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2])


def _sheet_tiles(
    surface: np.ndarray,
    band: np.ndarray,
    pixels: tuple[np.ndarray, np.ndarray],
    h: float,
    tile_m: float,
) -> tuple[np.ndarray, float]:
    """The expected number of tiles that the union of the blocks' band boxes meets (see the
    module's note): per block from its vector area and its box's extents, and in all from
    the sheet's boundary."""
    q = (surface[:-1, :-1], surface[:-1, 1:], surface[1:, 1:], surface[1:, :-1])
    # the four triangles that leave one corner out sum to twice the quad's vector area; a
    # block with one invalid corner keeps the triangle of the other three (NaN: missing)
    area = np.zeros(q[0].shape)
    n_tri = np.zeros(q[0].shape[:2])
    for k in range(4):
        a, b, c = q[(k + 1) % 4], q[(k + 2) % 4], q[(k + 3) % 4]
        tri = 0.5 * np.cross(b - a, c - a)
        ok = np.isfinite(tri[..., 0])
        area += np.where(ok[..., None], tri, 0.0)
        n_tri += ok
    use = n_tri > 0
    # (one triangle: the parallelogram it spans, as a lone invalid pixel leaves the rest)
    area = area[use] * np.where(n_tri[use] == 4, 0.5, 2.0)[:, None]
    # sides along u and v (the parallel one where a corner is missing)
    side_u = _either(q[1] - q[0], q[2] - q[3])[use]
    side_v = _either(q[3] - q[0], q[2] - q[1])[use]
    # extents of a quad's band box: the band along the line of sight, one pixel quad's
    # sides (a piece of at most half a tile), the widening to the next voxel centre
    c = np.stack([band[:-1, :-1], band[:-1, 1:], band[1:, 1:], band[1:, :-1]])
    c = np.abs(np.nanmean(np.where(use[None, ..., None], c, 0.0), axis=0)[use])
    per_pixel = np.minimum(np.abs(side_u) / pixels[0][use][:, None], 0.5 * tile_m)
    per_pixel += np.minimum(np.abs(side_v) / pixels[1][use][:, None], 0.5 * tile_m)
    G = c + per_pixel + h + tile_m
    interior = np.sum(np.abs(area) * G, axis=1)
    # the sides on the sheet's boundary (image border, unused neighbours); an unused
    # neighbour inside the image (a silhouette crosses it) holds about half a block of sheet
    edges = 0.0
    padded = np.pad(use, 1)
    inside = np.pad(use, 1, constant_values=True)
    lost = 0.0
    for side, out, border in (
        (side_u, ~padded[:-2, 1:-1], ~inside[:-2, 1:-1]),  # top
        (side_u, ~padded[2:, 1:-1], ~inside[2:, 1:-1]),  # bottom
        (side_v, ~padded[1:-1, :-2], ~inside[1:-1, :-2]),  # left
        (side_v, ~padded[1:-1, 2:], ~inside[1:-1, 2:]),  # right
    ):
        lost += 0.5 * float(np.sum(interior[border[use]]))
        o = out[use]
        e = np.abs(side[o])
        g = G[o]
        edges += 0.5 * float(np.sum(e[:, 0] * g[:, 1] * g[:, 2] + e[:, 1] * g[:, 0] * g[:, 2]
                                    + e[:, 2] * g[:, 0] * g[:, 1]))  # fmt: skip
    corner = float(np.prod(G.mean(axis=0))) if len(G) else 0.0
    blocks = np.zeros(use.shape)
    blocks[use] = interior / tile_m**3
    return blocks, (lost + edges + corner) / tile_m**3


def _step_tiles(
    scan: Scan,
    B_W: np.ndarray,
    du: np.ndarray,
    noise: NoiseModel,
    margin: float,
    max_disc: float | None,
    tile_m: float,
    blocks: tuple[np.ndarray, np.ndarray],
) -> tuple[float, np.ndarray]:
    """Tiles of the pixel quads across depth steps, at full resolution: a lone outlier (a
    spike, a flying pixel) or a thin object between the sampled pixels allocates a column
    of tiles along its line of sight that the blocks do not see. Quads in one bin of about
    a tile's width in pixels share their columns. Also which blocks (their first sampled
    rows and columns: ``blocks``) hold a step.

    The image is read in stripes of rows (:data:`_STRIPE_PIXELS` quads at a time), so that
    the memory it takes stays a few stripes whatever the image's size: a 4096 x 4096 map
    took 470 to 610 MB in one piece."""
    kind, p, _ = scan.sensor.kernel_args()
    wrap = _wraps(kind, p)  # the quad between the last column and the first
    n_rows = scan.range_m.shape[0] - 1
    width = scan.range_m.shape[1] - (0 if wrap else 1)
    stripe = max(1, _STRIPE_PIXELS // max(width, 1))
    step = np.zeros((max(n_rows, 0), max(width, 0)), np.bool_)
    n_step, lo_sum = 0, 0.0
    for q0 in range(0, n_rows, stripe):
        q1 = min(n_rows, q0 + stripe)
        lo, spread = _quads(scan.range_m, wrap, max(0, q0 - 1), min(n_rows, q1 + 1))
        top = q0 - max(0, q0 - 1)  # the rows of spread above and below this stripe's own
        nb = np.pad(spread, ((1 - top, 1 - (min(n_rows, q1 + 1) - q1)), (1, 1)),
                    constant_values=np.nan)  # fmt: skip
        # nb: this stripe's rows with one row of neighbours (or NaN) above and below
        least = np.fmin(np.fmin(nb[:-2, 1:-1], nb[2:, 1:-1]), np.fmin(nb[1:-1, :-2], nb[1:-1, 2:]))
        spread_own, lo_own = spread[top : top + q1 - q0], lo[top : top + q1 - q0]
        with np.errstate(invalid="ignore"):
            # a step: across more than half a tile, and three times its least neighbour's
            # spread (a surface seen at a grazing angle spreads about as much in its neighbours)
            here = (spread_own > 0.5 * tile_m) & ~(spread_own <= 3.0 * least)
            if max_disc is not None:  # such quads are invalid: they allocate nothing
                here &= spread_own <= max_disc
        step[q0:q1] = here
        n_step += int(np.count_nonzero(here))
        lo_sum += float(np.sum(lo_own[here], dtype=np.float64))
    starts = blocks
    in_block = np.logical_or.reduceat(
        np.logical_or.reduceat(step, starts[0], axis=0), starts[1], axis=1
    )  # bool throughout: add.reduceat would make an int64 copy of the image
    if not in_block.any():
        return 0.0, in_block
    # the angle between neighbouring pixels, and how many pixels a tile spans at a range
    pitch = float(np.median(np.linalg.norm(np.diff(B_W, axis=1), axis=-1) / du[None, :]))
    typical = lo_sum / n_step
    pixels = max(1, int(tile_m / max(typical * pitch, 1e-12)))
    # per bin of pixels x pixels quads, in stripes of whole bins
    parts: list[list[np.ndarray]] = [[], [], [], [], []]
    rows_per = pixels * max(1, stripe // pixels)
    for q0 in range(0, n_rows, rows_per):
        q1 = min(n_rows, q0 + rows_per)
        lo, spread = _quads(scan.range_m, wrap, q0, q1)
        here = step[q0:q1]
        n = _bins(here, pixels, np.add)
        has = n > 0
        parts[0].append(n[has])
        parts[1].append(_bins(np.where(here, spread, 0.0), pixels, np.maximum)[has])
        parts[2].append(_bins(np.where(here, lo, 0.0), pixels, np.add)[has])
        # rows and columns of the image with steps in each bin: its steps' extent across
        parts[3].append(_bins(_bins(here, (1, pixels), np.add) > 0, (pixels, 1), np.add)[has])
        parts[4].append(_bins(_bins(here, (pixels, 1), np.add) > 0, (1, pixels), np.add)[has])
    count, longest, lo_total, rows, cols = (np.concatenate(x) for x in parts)
    mean_range = lo_total / count
    eps = noise.eps + noise.eps_per_m * mean_range
    falloff = eps if noise.falloff is None else noise.falloff
    length = (longest + 2.0 * eps + falloff + margin) * _boxed_length(B_W) / tile_m + 1.0
    pixel = mean_range * pitch / tile_m
    return float(np.sum(length * (rows * pixel + 1.0) * (cols * pixel + 1.0))), in_block


#: Quads read at a time by :func:`_step_tiles` (about 4 MB per float32 array).
_STRIPE_PIXELS = 1 << 20


def _quads(range_m: np.ndarray, wrap: bool, q0: int, q1: int) -> tuple[np.ndarray, np.ndarray]:
    """The least range and the spread of each pixel quad of rows ``q0`` to ``q1`` (a quad
    row q spans image rows q and q + 1); no return (+inf) is no surface (NaN)."""
    r = range_m[q0 : q1 + 1]
    if wrap:
        r = np.concatenate([r, r[:, :1]], axis=1)
    with np.errstate(invalid="ignore"):
        r = np.where(r < np.inf, r, np.float32(np.nan))
        a, b, c, d = r[:-1, :-1], r[:-1, 1:], r[1:, :-1], r[1:, 1:]
        lo = np.minimum(np.minimum(a, b), np.minimum(c, d))
        spread = np.maximum(np.maximum(a, b), np.maximum(c, d)) - lo
    return lo, spread


def _bins(x: np.ndarray, size: int | tuple[int, int], reduce: np.ufunc) -> np.ndarray:
    """``reduce`` over bins of ``size`` pixels (rows, columns) of ``x``, the last ones partial
    (padded with zeros: for sums and maxima of non-negative values)."""
    bv, bu = (size, size) if isinstance(size, int) else size
    if bv == bu == 1:
        return x.astype(np.float64)
    nv, nu = -(-x.shape[0] // bv), -(-x.shape[1] // bu)
    padded = np.zeros((nv * bv, nu * bu), np.float64 if x.dtype != np.bool_ else np.int64)
    padded[: x.shape[0], : x.shape[1]] = x
    return reduce.reduce(reduce.reduce(padded.reshape(nv, bv, nu, bu), axis=3), axis=1)


def _boxed_length(B_W: np.ndarray) -> float:
    """Tiles per tile length along a line of sight (mean over the sampled ones) that the
    allocation's boxes of half-tile slabs of it meet: ``sum_k |d_k| (1 + |d_j| / 2)
    (1 + |d_l| / 2)`` for the unit direction ``d`` (a Minkowski sum), times ``|B|``."""
    norm = np.linalg.norm(B_W, axis=-1, keepdims=True)
    d = np.abs(B_W / norm).reshape(-1, 3)
    half = 1.0 + 0.5 * d
    boxed = d[:, 0] * half[:, 1] * half[:, 2] + d[:, 1] * half[:, 0] * half[:, 2]
    boxed += d[:, 2] * half[:, 0] * half[:, 1]
    return float(np.mean(boxed * norm.reshape(-1)))


def _either(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(x), x, y)
