"""Edge refinement (METHOD §3; ``docs/meshing.md``): where the surface crosses a cube edge,
from the scans themselves.

The paper notes that fusion pushes values towards 0 and 1, so linear interpolation of the
fused field places vertices badly. :func:`refine_edges` re-evaluates every scan that sees a
crossing edge at ``n_samples - 1`` points inside it, summing the same quantised
contributions the volume holds (so the result depends only on the edge and the scans), and
:func:`edge_crossings` places the vertex at the first crossing of ``L = 0`` along the samples.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable

import numpy as np
from numba import njit, prange

from ._sampling import point_contribution
from .certainty import pack
from .classify import FREE, OUT, classify_tiles
from .defaults import COUNT_BITS
from .grid import GridSpec
from .scans import PreparedScan

__all__ = ["edge_crossings", "refine_edges"]

_COUNT_MASK = (1 << COUNT_BITS) - 1


@functools.cache
def _sample_kernel(kind: int, shape: int):
    """Adds one scan's packed contributions at the inner sample points of edges."""

    @njit(cache=True, parallel=True)
    def sample(
        vkey,
        rows,
        h,
        n_samples,
        M,
        c,
        params,
        table,
        rng,
        eps0,
        eps1,
        rho,
        falloff,
        q_rho,
        max_disc,
        acc,
    ):
        for m in prange(rows.shape[0]):
            v = rows[m]
            axis = vkey[v, 3]
            # the edge in the sensor frame: p(s) = p0 + s * dp
            x = (vkey[v, 0] + 0.5) * h
            y = (vkey[v, 1] + 0.5) * h
            z = (vkey[v, 2] + 0.5) * h
            p0x = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + c[0]
            p0y = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + c[1]
            p0z = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + c[2]
            step = h / n_samples
            dx = M[0, axis] * step
            dy = M[1, axis] * step
            dz = M[2, axis] * step
            for s in range(1, n_samples):
                q, inf = point_contribution(
                    kind, shape, params, table, rng, max_disc, eps0, eps1, rho,
                    falloff, q_rho, p0x + s * dx, p0y + s * dy, p0z + s * dz,
                )  # fmt: skip
                if inf:
                    acc[v, s - 1] += pack(q)

    return sample


@njit(cache=True)
def _add_constant(acc, rows, value):
    for m in range(rows.shape[0]):
        for s in range(acc.shape[1]):
            acc[rows[m], s] += value


@njit(cache=True, parallel=True)
def edge_crossings(vlo, vhi, vknown, acc, n_samples, t_out):
    """Position of each vertex along its edge, in [0, 1]."""
    for v in prange(vlo.shape[0]):
        lo = vlo[v]
        hi = vhi[v]
        linear = lo / (lo - hi)
        if acc.shape[0] == 0 or not vknown[v]:
            t_out[v] = linear
            continue
        ok = True
        for s in range(n_samples - 1):
            if acc[v, s] & _COUNT_MASK == 0:
                ok = False  # an uninformed point on the edge: keep the linear position
                break
        if not ok:
            t_out[v] = linear
            continue
        prev = lo
        t = linear
        for s in range(1, n_samples + 1):
            cur = hi if s == n_samples else acc[v, s - 1] >> COUNT_BITS
            if (prev > 0) != (cur > 0):
                t = (s - 1 + prev / (prev - cur)) / n_samples
                break
            prev = cur
        t_out[v] = t


def refine_edges(
    tm_keys: np.ndarray,
    v_off: np.ndarray,
    vkey: np.ndarray,
    vknown: np.ndarray,
    scans: Iterable[PreparedScan],
    grid: GridSpec,
    n_samples: int,
) -> np.ndarray:
    """Packed fused contributions at the inner sample points of every refinable edge."""
    acc = np.zeros((len(vkey), n_samples - 1), np.int64)
    has_vertex = np.flatnonzero(np.diff(v_off) > 0)
    tile_of = np.repeat(np.arange(len(has_vertex)), np.diff(v_off)[has_vertex])
    for scan in scans:
        status = classify_tiles(scan, grid, tm_keys[has_vertex], halo=1)
        vstatus = status[tile_of]
        free_rows = np.flatnonzero((vstatus == FREE) & vknown)
        if len(free_rows):
            _add_constant(acc, free_rows, int(pack(np.int64(scan.q_rho))))
        rows = np.flatnonzero((vstatus != OUT) & (vstatus != FREE) & vknown)
        if len(rows) == 0:
            continue
        _sample_kernel(scan.kind, scan.shape)(
            vkey,
            rows,
            grid.voxel_size,
            n_samples,
            scan.M,
            scan.c,
            scan.params,
            scan.table,
            scan.range_m,
            scan.eps,
            scan.eps_per_m,
            scan.rho,
            scan.falloff,
            scan.q_rho,
            scan.max_discontinuity,
            acc,
        )
    return acc
