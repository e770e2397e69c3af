"""The parts of a LiDAR's partial tile, inside the fusion kernel (``docs/lidar.md``).

:func:`engine.fusion._integrate_kernel` tests the eight 8^3 parts of a spherical or cylindrical
sensor's partial tile (:func:`_see_part`), and a spherical sensor's partial parts again in eight
4^3 sub-parts, before any voxel: a part out of view or behind the surface beyond the reach is
skipped, a part free throughout takes ``logit(rho)`` (:func:`_add_block`), and what is left goes
through passes 1 and 2 of the kernel block by block (:func:`_fuse_block`). Each voxel receives
what the voxel loop gives it: the part tests are conservative (:mod:`engine.classify`).
"""

from __future__ import annotations

import math

from numba import njit

from ._sampling import column_ranges, prefetch_quad, quad_columns, quad_index
from ._sensor_kernels import (
    COLUMN_UNSURE,
    ROW_OUTSIDE,
    ROW_TAN_MARGIN,
    ROW_TAN_MAX,
    ROW_UNSURE,
    SPHERICAL,
    azimuth_column,
    column_of_direction,
    project_point,
    row_of_tangent,
    spherical_column,
    spherical_in_column,
    wraps,
)
from .classify import _classify_part, _classify_tile

#: Rows of a tile's table of level columns (:func:`level_column`).
_COL_STATE, _COL_U, _COL_RHO = range(3)
#: States of a column in that table: not yet computed, computed, or on an axis of the sensor
#: frame (its ``x`` or ``y`` is 0: the sign of that zero depends on the voxel's height).
COL_UNKNOWN, COL_KNOWN, COL_ON_AXIS = 0.0, 1.0, 2.0


@njit(cache=True, inline="always")
def level_column(cols, n, params, bx, by):
    """Whether column ``n`` of a tile (``cols``: 3 x T^2, the rows above) has its ``u`` and
    ``rho`` in ``cols``, computed the first time a block of the tile asks for it: a level
    spherical sensor's column of voxels shares its sensor-frame ``x`` and ``y`` (``bx``,
    ``by``), so :func:`~engine._sensor_kernels.spherical_column` of them is that of each of
    its voxels, bit for bit. A column with ``x`` or ``y`` exactly 0 is not kept (each voxel
    computes its own: ``x + 0.0 * z`` can change the sign of a zero)."""
    state = cols[_COL_STATE, n]
    if state == COL_UNKNOWN:
        if bx != 0.0 and by != 0.0:
            cu, rho = spherical_column(params, bx, by)
            cols[_COL_U, n] = cu
            cols[_COL_RHO, n] = rho
            state = COL_KNOWN
        else:
            state = COL_ON_AXIS
        cols[_COL_STATE, n] = state
    return state == COL_KNOWN


@njit(cache=True, inline="always")
def _add_block(tile, corner, S, T, value):
    # ``value`` to the S^3 voxels of the flat tile (side T) whose first voxel is tile[corner]
    for a in range(S):
        for b in range(S):
            line = corner + a * T * T + b * T
            for cc in range(S):
                tile[line + cc] += value


@njit(cache=True, inline="always")
def _see_part(
    kind, key, S, h, M, c, o_W, params, table, flat_bounds, p_reach, p_free, p_levels,
    reach_max, nqu, nqv, linear, lo, hi, acc,
):  # fmt: skip
    # how the scan sees the part ``key`` of S^3 voxels of a tile (engine.classify)
    if kind == SPHERICAL:
        return _classify_part(
            key, S, h, M, c, o_W, params, table, flat_bounds, p_reach, p_free, p_levels,
            reach_max, nqu, nqv, linear, lo, hi, acc,
        )  # fmt: skip
    return _classify_tile(
        kind, key, S, 0.0, h, M, c, o_W, params, table, p_reach, p_free, p_levels, reach_max,
        nqu, nqv, linear, lo, hi, acc,
    )  # fmt: skip


#: Outcomes of :func:`_band_outcome`.
BAND_UNSURE, BAND_FREE, BAND_NOTHING = 0, 1, 2
#: Relative margin of :func:`_band_outcome`'s bounds for the rounding of the exact path
#: (the bilinear range, ``alpha`` and ``eps`` err by a few ulps: about 1e-15).
BAND_MARGIN = 1e-9


@njit(cache=True, inline="always", error_model="numpy")
def _band_outcome(rng, qu, r, u, fv, slack, d, fit, linear):
    # What pass 3 will give a band voxel of a spherical sensor in quad (qu, r), decided
    # without its elevation's atan2 where the answer is sure: BAND_NOTHING (beyond the
    # reach), BAND_FREE (logit(rho), linear shape) or BAND_UNSURE. ``u``: the voxel's exact
    # column; ``fv``: its fraction of the row from the row's chord, within ``slack``
    # (engine._sensor_kernels.row_chords). At a fixed u the bilinear range is affine in fv
    # between the column's ranges on the two rows, so it lies between its values at the
    # ends of fv's interval; ``alpha > eps + f`` (nothing) and ``alpha < -eps`` (free) only
    # get truer as the range falls, resp. grows (eps = eps0 + eps1 r, 0 <= eps1 < 1), so
    # each is tested at the end of the range's interval where it is least true.
    top, bottom = column_ranges(rng, qu, r, u)  # bilinear's, exactly
    f_lo = max(fv - slack, 0.0)
    f_hi = min(fv + slack, 1.0)
    r_a = top + f_lo * (bottom - top)
    r_b = top + f_hi * (bottom - top)
    margin = BAND_MARGIN * (abs(top) + abs(bottom))
    r_lo = min(r_a, r_b) - margin
    r_hi = max(r_a, r_b) + margin
    margin = BAND_MARGIN * (d + abs(top) + abs(bottom) + 1.0)
    eps0 = fit[0]
    eps1 = fit[1]
    eps_hi = eps0 + eps1 * r_hi
    f = fit[2] if fit[2] > 0.0 else eps_hi
    if d - r_hi - eps_hi - f > margin:
        return BAND_NOTHING
    if linear and d - r_lo + eps0 + eps1 * r_lo < -margin:
        return BAND_FREE
    return BAND_UNSURE


#: Outcomes of :func:`_run_outcome`.
RUN_UNSURE, RUN_FREE, RUN_NOTHING = 0, 1, 2


@njit(cache=True, inline="always", error_model="numpy")
def _run_outcome(linear, tans, chords, fit, flat_bounds, rng, cu, q0, rho, z_a, z_b, nqu, row):
    # What _fuse_spherical gives each voxel of a level column's run (the S voxels of a
    # block's column: one column cu, quad column q0 >= 0 and distance from the axis rho;
    # sensor-frame heights z_a and z_b at its ends, computed as the voxel loop computes
    # them), when it is the same sure answer for all: RUN_FREE (each takes logit(rho)),
    # RUN_NOTHING, or RUN_UNSURE (go voxel by voxel); and the quad row the loop would leave.
    # Every quantity a voxel's tests read is monotone in its height, and rounding is
    # monotone, so each voxel's lies between the run's ends: its tangent t, its distance
    # d, and its fraction fv of the row. A test sure at the least favourable end, with the
    # largest margin of the run, is sure for every voxel of it.
    t_a = z_a / rho
    t_b = z_b / rho
    t_lo = min(t_a, t_b)
    t_hi = max(t_a, t_b)
    n = tans.shape[0]
    steep = max(abs(t_lo), abs(t_hi))
    if not steep <= ROW_TAN_MAX:
        return RUN_UNSURE, row
    margin = ROW_TAN_MARGIN * max(1.0, steep)  # row_of_tangent's, at the steepest voxel
    if t_lo - tans[0] > margin or tans[n - 1] - t_hi > margin:
        return RUN_NOTHING, row  # above the first row or below the last throughout
    r = row_of_tangent(tans, t_lo, row)
    if r < 0 or not (tans[r] - t_hi > margin and t_lo - tans[r + 1] > margin):
        return RUN_UNSURE, row  # not one sure row for the whole run
    q = q0 + r * nqu
    lo = flat_bounds[2 * q]
    hi = flat_bounds[2 * q + 1]
    z_far = max(abs(z_a), abs(z_b))
    z_near = 0.0 if (z_a < 0.0) != (z_b < 0.0) else min(abs(z_a), abs(z_b))
    d_max = math.sqrt(rho * rho + z_far * z_far)  # as _fuse_spherical, at either end
    d_min = math.sqrt(rho * rho + z_near * z_near)
    if linear and d_max < lo:
        return RUN_FREE, r
    if d_min > hi:  # lo <= hi: none is free either
        return RUN_NOTHING, r
    if chords.shape[1] == 0:
        return RUN_UNSURE, r
    # _band_outcome over the run: fv spans its values at the two ends; its bounds are
    # tested at the run's extreme distances with twice the margin at the farthest (the
    # margins cover the rounding of the voxel's own test). A voxel it settles as nothing
    # cannot be free by the quad's bounds (lo is below every range of the quad), nor one
    # it settles as free beyond them (hi is above).
    slack = chords[1, r]
    top, bottom = column_ranges(rng, q0, r, cu)
    f_lo = max((tans[r] - t_hi) * chords[0, r] - slack, 0.0)
    f_hi = min((tans[r] - t_lo) * chords[0, r] + slack, 1.0)
    r_a = top + f_lo * (bottom - top)
    r_b = top + f_hi * (bottom - top)
    m = BAND_MARGIN * (abs(top) + abs(bottom))
    r_lo = min(r_a, r_b) - m
    r_hi = max(r_a, r_b) + m
    m = 2.0 * BAND_MARGIN * (d_max + abs(top) + abs(bottom) + 1.0)
    eps0 = fit[0]
    eps1 = fit[1]
    eps_hi = eps0 + eps1 * r_hi
    f = fit[2] if fit[2] > 0.0 else eps_hi
    if d_min - r_hi - eps_hi - f > m:
        return RUN_NOTHING, r
    if linear and d_max - r_lo + eps0 + eps1 * r_lo < -m:
        return RUN_FREE, r
    return RUN_UNSURE, r


@njit(cache=True, inline="always", error_model="numpy")
def _fuse_spherical(
    linear, params, table, tans, chords, fit, flat_bounds, rng, tile, index, cu, q0, x, y, rho,
    z, row, nqu, free_value, at, band_u, band_v, band_d, count, queued,
):  # fmt: skip
    # passes 1 and 2 at once for the voxel tile[index] of a spherical sensor, its column cu,
    # its distance from the axis rho and its height z in the sensor frame known (q0: the
    # column's quad in row 0, -1 outside the image; cu NaN: not computed yet, then from the
    # voxel's sensor-frame x and y where it is needed). The quad row comes from the tangent of
    # the elevation (row_of_tangent), so that only a voxel in the band, or within a margin
    # of a row's edge, takes the elevation's atan2; a band voxel whose outcome is sure from
    # its row's chord (_band_outcome: ``chords`` from row_chords, empty when not used;
    # ``fit``: eps0, eps1 and the falloff) does not either. Returns count, queued and the row.
    if q0 < 0:
        return count, queued, row
    t = z / rho
    r = row_of_tangent(tans, t, row)
    if r == ROW_OUTSIDE:
        return count, queued, row
    if r == ROW_UNSURE:
        if cu != cu:
            cu = azimuth_column(params, x, y)
        u, v, d = spherical_in_column(params, table, cu, rho, z)
        q = quad_index(SPHERICAL, params, u, v)
        if q < 0:
            return count, queued, row
    else:
        row = r
        q = q0 + r * nqu
        d = math.sqrt(rho * rho + z * z)  # as spherical_in_column
    if linear and d < flat_bounds[2 * q]:
        tile[index] += free_value
        count += 1
    elif d <= flat_bounds[2 * q + 1]:
        if cu != cu:
            cu = azimuth_column(params, x, y)
        if r >= 0 and chords.shape[1] > 0:
            outcome = _band_outcome(
                rng, q0, r, cu, (tans[r] - t) * chords[0, r], chords[1, r], d, fit, linear
            )
            if outcome == BAND_FREE:
                tile[index] += free_value
                return count + 1, queued, row
            if outcome == BAND_NOTHING:
                return count, queued, row
        u, v, d = spherical_in_column(params, table, cu, rho, z)
        at[queued] = index
        band_u[queued] = u
        band_v[queued] = v
        band_d[queued] = d
        queued += 1
        prefetch_quad(SPHERICAL, params, rng, u, v)
    return count, queued, row


@njit(cache=True, inline="always", error_model="numpy")
def _fuse_block(
    kind, linear, tile, block, T, h, M, c, params, table, tans, chords, fit, edges, flat_bounds,
    rng, free_value, at, band_u, band_v, band_d, slab_y, slab_z, slab_u, slab_v, slab_d, slab_q,
    cols, count, queued,
):  # fmt: skip
    # passes 1 and 2 (see _integrate_kernel) over the block of S^3 voxels whose first voxel is
    # ``tile[corner]``, voxel (i, j, k) of the grid (``block``: a row of _push); returns the
    # new count and queue length (``tans``: the sensor's row_tangents, empty if not
    # spherical; ``cols``: the tile's level columns, level_column)
    i = block[0]
    j = block[1]
    k = block[2]
    S = block[3]
    corner = block[4]
    TT = T * T
    for b in range(S):
        y = ((j + b) + 0.5) * h
        for cc in range(S):
            slab_y[b * S + cc] = y
            slab_z[b * S + cc] = ((k + cc) + 0.5) * h
    if kind == SPHERICAL and tans.shape[0] > 0:
        # voxel by voxel, passes 1 and 2 at once (_fuse_spherical). A level sensor (no roll
        # or pitch: the world's z does not move a point's x and y in the sensor frame) sees
        # a column of voxels at one azimuth and one distance from its axis: computed once per
        # column of the tile (level_column; x + 0.0 * z is x unless x is zero: those columns
        # go voxel by voxel, as the sign of a zero can change the azimuth)
        level = cols.shape[1] > 0
        nqu = quad_columns(kind, params)
        wrap = wraps(kind, params)
        row = 0
        last_k = 0
        # a level column's run of S voxels is settled at once where it is sure
        # (_run_outcome), tried only where it spans under half a row's mean tangent step:
        # longer runs (near the sensor) mostly cross a row, and paid the test for nothing
        H = tans.shape[0]
        span = (S - 1) * h
        step = 0.5 * (tans[0] - tans[H - 1]) / (H - 1) if H > 1 and S > 1 else 0.0
        for a in range(S):
            x = ((i + a) + 0.5) * h
            base = corner + a * TT
            for b in range(S):
                first = b * S
                bx = M[0, 0] * x + M[0, 1] * slab_y[first] + c[0]
                by = M[1, 0] * x + M[1, 1] * slab_y[first] + c[1]
                bz = M[2, 0] * x + M[2, 1] * slab_y[first] + c[2]
                n = ((i + a) % T) * T + (j + b) % T
                column = level and level_column(cols, n, params, bx, by)
                if column:
                    cu = cols[_COL_U, n]
                    rho = cols[_COL_RHO, n]
                    q0 = quad_index(kind, params, cu, 0.0)
                    if q0 >= 0 and span < step * rho:
                        outcome, row = _run_outcome(
                            linear, tans, chords, fit, flat_bounds, rng, cu, q0, rho,
                            bz + M[2, 2] * slab_z[first], bz + M[2, 2] * slab_z[first + S - 1],
                            nqu, row,
                        )  # fmt: skip
                        if outcome == RUN_FREE:
                            line = base + b * T
                            for cc in range(S):
                                tile[line + cc] += free_value
                            count += S
                            continue
                        if outcome == RUN_NOTHING:
                            continue
                px = bx
                py = by
                for cc in range(S):
                    z = slab_z[first + cc]
                    if not column:
                        # a tilted pose's voxel (or one on an axis): its quad column from its
                        # direction where sure, its exact column then only where needed
                        px = bx + M[0, 2] * z
                        py = by + M[1, 2] * z
                        rho = math.sqrt(px * px + py * py)  # as spherical_column
                        k = COLUMN_UNSURE
                        if edges.shape[1] > 0:
                            k = column_of_direction(edges, px, py, rho, last_k, wrap)
                        if k >= 0:
                            cu = math.nan
                            q0 = k
                            last_k = k
                        else:
                            cu = azimuth_column(params, px, py)
                            q0 = quad_index(kind, params, cu, 0.0)
                            if q0 >= 0:  # the next voxel's walk starts here
                                last_k = q0
                    count, queued, row = _fuse_spherical(
                        linear, params, table, tans, chords, fit, flat_bounds, rng, tile,
                        base + b * T + cc, cu, q0, px, py, rho, bz + M[2, 2] * z, row, nqu,
                        free_value, at, band_u, band_v, band_d, count, queued,
                    )  # fmt: skip
        return count, queued
    for a in range(S):
        x = ((i + a) + 0.5) * h
        for b in range(S):  # pass 1
            first = b * S
            bx = M[0, 0] * x + M[0, 1] * slab_y[first] + c[0]
            by = M[1, 0] * x + M[1, 1] * slab_y[first] + c[1]
            bz = M[2, 0] * x + M[2, 1] * slab_y[first] + c[2]
            for m in range(first, first + S):
                z = slab_z[m]
                u, v, d = project_point(
                    kind, params, table, bx + M[0, 2] * z, by + M[1, 2] * z, bz + M[2, 2] * z
                )
                slab_u[m] = u
                slab_v[m] = v
                slab_d[m] = d
                slab_q[m] = quad_index(kind, params, u, v)
        base = corner + a * TT
        for b in range(S):  # pass 2
            for cc in range(S):
                m = b * S + cc
                q = slab_q[m]
                if q < 0:
                    continue
                d = slab_d[m]
                if linear and d < flat_bounds[2 * q]:
                    tile[base + b * T + cc] += free_value
                    count += 1
                elif d <= flat_bounds[2 * q + 1]:
                    u = slab_u[m]
                    v = slab_v[m]
                    at[queued] = base + b * T + cc
                    band_u[queued] = u
                    band_v[queued] = v
                    band_d[queued] = d
                    queued += 1
                    prefetch_quad(kind, params, rng, u, v)
    return count, queued


@njit(cache=True, inline="always")
def _push(blocks, n, i, j, k, S, corner):
    # a block of S^3 voxels left for _fuse_block: first voxel (i, j, k), at tile[corner]
    blocks[n, 0] = i
    blocks[n, 1] = j
    blocks[n, 2] = k
    blocks[n, 3] = S
    blocks[n, 4] = corner
    return n + 1
