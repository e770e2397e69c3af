"""Sensor geometry inside numba kernels.

A sensor reaches a kernel as a kind code, a float64 parameter vector and an
elevation table (empty unless a spherical sensor has one). The layout of the
parameter vector is fixed here; :mod:`engine.sensors` fills it.

``project_point`` maps a sensor-frame point to continuous pixel coordinates
``(u, v)`` (pixel centres at integers) and its line-of-sight distance ``d`` in
the sensor's range convention. It returns ``u = nan`` where the point has no
pixel at all (behind a pinhole camera, on a cylinder axis ...); whether
``(u, v)`` lies inside the image is the caller's test.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

PINHOLE = 0
SPHERICAL = 1
CYLINDRICAL = 2
ORTHOGRAPHIC = 3

# common parameters
P_W = 0
P_H = 1
P_MIN_RANGE = 2
P_MAX_RANGE = 3
# pinhole
P_FX = 4
P_FY = 5
P_CX = 6
P_CY = 7
P_Z_CONV = 8  # 1: z-depth, 0: ray range
# spherical and cylindrical columns
P_AZ_MIN = 4
P_DAZ = 5
P_WRAP = 6
# spherical rows
P_EL_MAX = 7
P_DEL = 8
P_HAS_TABLE = 9
# cylindrical rows
P_CYL_FY = 7
P_CYL_CY = 8
P_LINEAR = 9  # 1: rows linear along the axis, 0: perspective (z / hypot(x, y))
P_RADIAL = 10  # 1: range hypot(x, y), 0: ray range |p|
# orthographic
P_SX = 4
P_SY = 5
P_OCX = 6
P_OCY = 7

N_PARAMS = 11
TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def _column_from_azimuth(params, az):
    # Angle measured from az_min in [0, 2 pi), then in columns.
    a = (az - params[P_AZ_MIN]) % TWO_PI
    return a / params[P_DAZ]


#: Bins of the elevation table's index per row (see :func:`elevation_table`).
TABLE_BINS_PER_ROW = 8


def elevation_table(elevations: np.ndarray) -> np.ndarray:
    """The table kernels take for a spherical sensor with per-row elevations.

    ``[e_0 .. e_{H-1}, inv_w, n_bins, start_0 .. start_{n_bins - 1}]``: the H elevations
    (decreasing), then an index over ``n_bins`` equal bins of elevation from ``e_0``
    downwards (``inv_w`` bins per radian): ``start_b`` is the last row whose elevation is at
    or above the top of bin ``b``. :func:`_row_from_table` starts there and steps to the
    row a binary search finds (the same row, so the same ``v``), one or two steps instead
    of ``log2(H)`` unpredictable branches: about a third of a LiDAR voxel's projection.
    """
    e = np.ascontiguousarray(elevations, np.float64)
    n = e.shape[0]
    n_bins = TABLE_BINS_PER_ROW * n
    span = e[0] - e[n - 1]
    inv_w = n_bins / span
    tops = e[0] - np.arange(n_bins) / inv_w
    # last row with e[row] >= top: e is decreasing, so count the rows at or above it
    starts = np.searchsorted(-e, -tops, side="right") - 1
    starts = np.clip(starts, 0, n - 2).astype(np.float64)
    return np.concatenate([e, [inv_w, float(n_bins)], starts])


@njit(cache=True, inline="always")
def _row_from_table(table, n, el):
    # table holds n decreasing elevations (then its index: elevation_table); find v0 with
    # table[v0] >= el > table[v0 + 1] (the row a binary search finds), extrapolating
    # linearly from the end intervals.
    if el != el:
        return math.nan  # as the binary search gave: v0 = 0, then NaN
    if el >= table[0]:
        v0 = 0
    elif el <= table[n - 1]:
        v0 = n - 2
    else:
        n_bins = int(table[n + 1])
        b = int((table[0] - el) * table[n])  # el < table[0]: b >= 0
        if b > n_bins - 1:
            b = n_bins - 1
        v0 = int(table[n + 2 + b])
        while table[v0 + 1] >= el:  # stops by n - 2: table[n - 1] < el
            v0 += 1
        while table[v0] < el:  # stops by 0: table[0] > el
            v0 -= 1
    return v0 + (table[v0] - el) / (table[v0] - table[v0 + 1])


@njit(cache=True)
def _elevation_from_table(table, n, v):
    v0 = int(math.floor(v))
    if v0 < 0:
        v0 = 0
    elif v0 > n - 2:
        v0 = n - 2
    return table[v0] + (v - v0) * (table[v0 + 1] - table[v0])


@njit(cache=True, inline="always")
def project_point(kind, params, table, x, y, z):
    """Sensor-frame point -> (u, v, d); ``u`` is nan where there is no pixel."""
    nan = math.nan
    if kind == PINHOLE:
        if z <= 0.0:
            return nan, nan, nan
        u = params[P_FX] * x / z + params[P_CX]
        v = params[P_FY] * y / z + params[P_CY]
        if params[P_Z_CONV] != 0.0:
            d = z
        else:
            d = math.sqrt(x * x + y * y + z * z)
        return u, v, d
    if kind == SPHERICAL:
        u, rho = spherical_column(params, x, y)
        return spherical_in_column(params, table, u, rho, z)
    if kind == CYLINDRICAL:
        rho = math.sqrt(x * x + y * y)
        if rho == 0.0:
            return nan, nan, nan
        u = azimuth_column(params, x, y)
        if params[P_LINEAR] != 0.0:
            v = params[P_CYL_CY] - params[P_CYL_FY] * z
        else:
            v = params[P_CYL_CY] - params[P_CYL_FY] * z / rho
        if params[P_RADIAL] != 0.0:
            d = rho
        else:
            d = math.sqrt(rho * rho + z * z)
        return u, v, d
    # ORTHOGRAPHIC
    if z < 0.0:
        return nan, nan, nan
    return x / params[P_SX] + params[P_OCX], y / params[P_SY] + params[P_OCY], z


@njit(cache=True, inline="always")
def azimuth_column(params, x, y):
    """The column ``u`` of a spherical or cylindrical sensor's point ``(x, y, z)``, whatever
    its ``z``, as :func:`project_point` computes it."""
    return _column_from_azimuth(params, math.atan2(y, x))


@njit(cache=True, inline="always")
def spherical_column(params, x, y):
    """A spherical sensor's column ``u`` and distance from the axis ``rho`` of the point
    ``(x, y, z)`` whatever its ``z``, as :func:`project_point` computes them."""
    return azimuth_column(params, x, y), math.sqrt(x * x + y * y)


@njit(cache=True, inline="always")
def spherical_in_column(params, table, u, rho, z):
    """:func:`project_point` for a spherical sensor, the point's column ``u`` and ``rho``
    known (:func:`spherical_column`): one ``atan2`` and one square root, the column's are
    computed once for a level column of voxels (``project_point`` calls the two)."""
    d = math.sqrt(rho * rho + z * z)
    if d == 0.0:
        return math.nan, math.nan, math.nan
    el = math.atan2(z, rho)
    if params[P_HAS_TABLE] != 0.0:
        v = _row_from_table(table, int(params[P_H]), el)
    else:
        v = (params[P_EL_MAX] - el) / params[P_DEL]
    return u, v, d


#: A spherical sensor's point is put in its quad row by its tangent ``z / rho`` against the
#: rows' tangents (:func:`row_of_tangent`, no ``atan2``) when it lies at least this much,
#: relative to ``max(1, |t|)``, from every row's tangent: ``atan2`` and the rows' arithmetic
#: err by a few ulps (about 1e-16 relative), so the row is the one ``project_point`` gives.
ROW_TAN_MARGIN = 1e-9
#: Steeper points (``|z / rho|`` above this) go through ``atan2``: there a tangent margin
#: shrinks to an elevation margin of about ``ROW_TAN_MARGIN / |t|``.
ROW_TAN_MAX = 1e3
#: :func:`row_of_tangent`'s answers besides a row.
ROW_OUTSIDE = -1
ROW_UNSURE = -2


@njit(cache=True)
def row_tangents(params, table):
    """The tangents of a spherical sensor's row elevations (where ``v`` is an integer),
    strictly decreasing; empty when they are not (rows that do not go down, or an
    elevation within 0.07 rad of a pole): then every point goes through ``atan2``."""
    H = int(params[P_H])
    out = np.empty(H)
    for b in range(H):
        if params[P_HAS_TABLE] != 0.0:
            el = table[b]
        else:
            el = params[P_EL_MAX] - b * params[P_DEL]
        if not abs(el) < 1.5:
            return np.empty(0)
        out[b] = math.tan(el)
    for b in range(H - 1):
        if not out[b] > out[b + 1]:
            return np.empty(0)
    return out


#: A spherical sensor's point is put in its quad column by its direction against the
#: directions of the columns' edges (:func:`column_of_direction`, no ``atan2``) when it lies
#: at least this much, relative to its distance from the axis, from each edge of its column:
#: ``atan2``, the column's arithmetic and the edges' ``cos`` and ``sin`` err by about 1e-15.
COL_DIR_MARGIN = 1e-9
#: :func:`column_of_direction`'s answer when it cannot say.
COLUMN_UNSURE = -2


@njit(cache=True)
def column_edges(params):
    """The directions ``(cos, sin)`` of a spherical sensor's column edges (where ``u`` is an
    integer, ``0 .. W - 1``), for :func:`column_of_direction`; empty when a column spans a
    quarter turn or more (then every point goes through ``atan2``)."""
    W = int(params[P_W])
    if not (W >= 2 and 0.0 < params[P_DAZ] < 0.5 * math.pi):
        return np.empty((2, 0))
    out = np.empty((2, W))
    for k in range(W):
        a = params[P_AZ_MIN] + k * params[P_DAZ]
        out[0, k] = math.cos(a)
        out[1, k] = math.sin(a)
    return out


@njit(cache=True, inline="always")
def column_of_direction(edges, x, y, rho, k, wrap):
    """The quad column of a spherical sensor's point whose sensor-frame ``x`` and ``y`` are
    given (``rho``: their hypot), as ``quad_index`` finds it from ``project_point``'s ``u``,
    or ``COLUMN_UNSURE``: within the margin of an edge, more than 8 steps from ``k`` (the
    last point's column, where the walk starts), or (a sensor that does not wrap) beyond its
    first or last quad. A direction strictly counter-clockwise of edge ``k`` and clockwise of
    edge ``k + 1`` (cross products beyond the margin) lies between them: the edges are less
    than a quarter turn apart."""
    W = edges.shape[1]
    last = W - 1 if wrap else W - 2  # the last quad column
    m = COL_DIR_MARGIN * rho
    k = min(max(k, 0), last)
    for _ in range(8):
        k1 = k + 1 if k + 1 < W else 0
        c0 = edges[0, k] * y - edges[1, k] * x
        if c0 <= m:  # not surely counter-clockwise of edge k: a column down
            if c0 > -m or (k == 0 and not wrap):
                return COLUMN_UNSURE
            k = k - 1 if k > 0 else W - 1
            continue
        c1 = edges[0, k1] * y - edges[1, k1] * x
        if c1 >= -m:  # not surely clockwise of edge k + 1: a column up
            if c1 < m or (k == last and not wrap):
                return COLUMN_UNSURE
            k = k1
            continue
        return k
    return COLUMN_UNSURE


#: The largest curvature of ``atan``: ``|atan''(t)| = 2 |t| / (1 + t^2)^2``, at most
#: ``3 sqrt(3) / 8`` (at ``t = 1 / sqrt(3)``).
_ATAN_CURVATURE = 3.0 * math.sqrt(3.0) / 8.0
#: Added to each row's chord bound (:func:`row_chords`): the rounding of ``atan2``, of the
#: division ``z / rho`` and of ``v``'s arithmetic is about 1e-15 of a row.
ROW_CHORD_SLACK = 1e-9


@njit(cache=True)
def row_chords(params, table, tans):
    """How far a spherical sensor's ``v`` can lie from a line in the tangent of the
    elevation, row by row (``tans``: :func:`row_tangents`, not empty). For a point of
    quad row ``r`` whose elevation has the tangent ``t``, ``fv = v - r`` lies within
    ``out[1, r]`` of the chord ``(tans[r] - t) * out[0, r]``: ``fv`` is ``(e_r - atan(t)) /
    (e_r - e_{r+1})`` and ``atan`` departs from its chord between ``tans[r + 1]`` and
    ``tans[r]`` by at most its curvature times ``(tans[r] - tans[r + 1])^2 / 8``."""
    H = tans.shape[0]
    out = np.empty((2, H - 1))
    for r in range(H - 1):
        if params[P_HAS_TABLE] != 0.0:
            gap = table[r] - table[r + 1]
        else:
            gap = params[P_DEL]
        dt = tans[r] - tans[r + 1]
        out[0, r] = 1.0 / dt
        out[1, r] = _ATAN_CURVATURE * dt * dt / 8.0 / gap + ROW_CHORD_SLACK
    return out


@njit(cache=True, inline="always")
def row_of_tangent(tans, t, r):
    """The quad row (``0 .. H - 2``) of a spherical sensor's point whose elevation has the
    tangent ``t``, as ``quad_index`` finds it from ``project_point``'s ``v``: ``ROW_OUTSIDE``
    above the first row or below the last, ``ROW_UNSURE`` when ``t`` is within the margin of
    a row's tangent (or too steep, or NaN). ``r``: a row to start the walk from (the last
    point's row: a column's points cross a few rows)."""
    n = tans.shape[0]
    a = abs(t)
    if not a <= ROW_TAN_MAX:
        return ROW_UNSURE
    margin = ROW_TAN_MARGIN * max(1.0, a)
    if t > tans[0]:
        return ROW_OUTSIDE if t - tans[0] > margin else ROW_UNSURE
    if t < tans[n - 1]:
        return ROW_OUTSIDE if tans[n - 1] - t > margin else ROW_UNSURE
    r = min(max(r, 0), n - 2)
    while r < n - 2 and tans[r + 1] >= t:
        r += 1
    while r > 0 and tans[r] < t:
        r -= 1
    # now tans[r] >= t >= tans[r + 1] (v in [r, r + 1]); sure when strictly inside
    if tans[r] - t > margin and t - tans[r + 1] > margin:
        return r
    return ROW_UNSURE


@njit(cache=True, inline="always")
def distance(kind, params, x, y, z):
    """The range ``d`` of a sensor-frame point in the sensor's convention (pixel or not)."""
    if kind == PINHOLE:
        if params[P_Z_CONV] != 0.0:
            return z
        return math.sqrt(x * x + y * y + z * z)
    if kind == SPHERICAL:
        return math.sqrt(x * x + y * y + z * z)
    if kind == CYLINDRICAL:
        if params[P_RADIAL] != 0.0:
            return math.sqrt(x * x + y * y)
        return math.sqrt(x * x + y * y + z * z)
    return z


@njit(cache=True, inline="always")
def unproject_point(kind, params, table, u, v, d):
    """(u, v, d) -> sensor-frame point; nan where no point has that range."""
    nan = math.nan
    if kind == PINHOLE:
        xn = (u - params[P_CX]) / params[P_FX]
        yn = (v - params[P_CY]) / params[P_FY]
        if params[P_Z_CONV] != 0.0:
            s = d
        else:
            s = d / math.sqrt(xn * xn + yn * yn + 1.0)
        return xn * s, yn * s, s
    if kind == SPHERICAL:
        az = params[P_AZ_MIN] + u * params[P_DAZ]
        if params[P_HAS_TABLE] != 0.0:
            el = _elevation_from_table(table, int(params[P_H]), v)
        else:
            el = params[P_EL_MAX] - v * params[P_DEL]
        c = math.cos(el)
        return d * c * math.cos(az), d * c * math.sin(az), d * math.sin(el)
    if kind == CYLINDRICAL:
        az = params[P_AZ_MIN] + u * params[P_DAZ]
        if params[P_LINEAR] != 0.0:
            z = (params[P_CYL_CY] - v) / params[P_CYL_FY]
            if params[P_RADIAL] != 0.0:
                rho = d
            else:
                q = d * d - z * z
                if q < 0.0:
                    return nan, nan, nan
                rho = math.sqrt(q)
        else:
            t = (params[P_CYL_CY] - v) / params[P_CYL_FY]
            if params[P_RADIAL] != 0.0:
                rho = d
            else:
                rho = d / math.sqrt(1.0 + t * t)
            z = t * rho
        return rho * math.cos(az), rho * math.sin(az), z
    # ORTHOGRAPHIC
    return (u - params[P_OCX]) * params[P_SX], (v - params[P_OCY]) * params[P_SY], d


@njit(cache=True, inline="always")
def wraps(kind, params):
    """True for a full-turn sensor whose columns wrap around."""
    return kind in (SPHERICAL, CYLINDRICAL) and params[P_WRAP] != 0.0


@njit(cache=True, inline="always")
def in_image(kind, params, u, v):
    """True when continuous pixel coordinates can be interpolated (METHOD exact conventions).

    Rows must lie in ``[0, H - 1]``; columns in ``[0, W - 1]``, or in ``[0, W)``
    for a wrapping sensor (between the last column and the first).
    """
    if not (v >= 0.0 and v <= params[P_H] - 1.0):
        return False
    if wraps(kind, params):
        return u >= 0.0 and u < params[P_W]
    return u >= 0.0 and u <= params[P_W] - 1.0


@njit(cache=True, parallel=True)
def project_many(kind, params, table, p_S, out):
    """Rows of ``p_S`` (n, 3) -> rows of ``out`` (n, 3) = (u, v, d)."""
    for n in prange(p_S.shape[0]):
        u, v, d = project_point(kind, params, table, p_S[n, 0], p_S[n, 1], p_S[n, 2])
        out[n, 0] = u
        out[n, 1] = v
        out[n, 2] = d


@njit(cache=True, parallel=True)
def unproject_many(kind, params, table, uvd, out):
    """Rows of ``uvd`` (n, 3) -> sensor-frame points in ``out`` (n, 3)."""
    for n in prange(uvd.shape[0]):
        x, y, z = unproject_point(kind, params, table, uvd[n, 0], uvd[n, 1], uvd[n, 2])
        out[n, 0] = x
        out[n, 1] = y
        out[n, 2] = z


def empty_table() -> np.ndarray:
    """The elevation table of a sensor that has none."""
    return np.zeros(0, dtype=np.float64)
