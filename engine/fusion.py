"""Fusion of scans into tiles (METHOD.md §2; DESIGN.md invariants 2-4).

Every voxel of a tile is projected into every scan that has the tile in view
(backward projection); the scan's certainty at the voxel centre becomes a
fixed-point log-odds contribution that is added to the voxel (or subtracted
when the scan is removed). Integer sums make the volume bit-identical whatever
the order of scans and however the tiles are split among threads.

:class:`Volume` keeps the bookkeeping that makes that true when scans arrive
one by one: a tile created by a late scan also receives every earlier scan
that has it in view, and a new scan also updates existing tiles it sees
through. :meth:`Volume.add_many` fuses a batch in two passes (allocate, then
integrate) with the same result.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ._memory import Scratch, zeros
from ._parts import COL_UNKNOWN, _add_block, _fuse_block, _push, _see_part
from ._sampling import bilinear, prefetch, prefetch_quad, quad_columns, quad_index, quad_origin
from ._sensor_kernels import (
    CYLINDRICAL,
    P_H,
    SPHERICAL,
    column_edges,
    project_point,
    row_chords,
    row_tangents,
)
from ._threads import warn_if_slow_threading
from .certainty import SHAPE_LINEAR, contribution, pack
from .classify import FREE, OUT, classify_tiles, reach_radius
from .errors import InvalidInputError, ScanNotFoundError
from .grid import GridSpec
from .meshing import Mesh, extract_mesh
from .planner import Sphere, plan_add, plan_remove
from .scans import FusionParams, PreparedScan, Scan, prepare_scan
from .spatial import SphereIndex
from .volume import DenseGrid, MemoryTileStore, TileStore, dense_logodds

__all__ = ["IntegrationReport", "Volume", "integrate_seen", "integrate_tiles"]

Progress = Callable[[int, int], None]

#: Voxels (int64) per 64-byte cache line: the kernel prefetches a slab line by line.
_LINE_VOXELS = 8
#: Sensor kinds whose kernel tests the eight parts of a partial tile before its voxels
#: (``docs/lidar.md``): a LiDAR voxel's projection (two ``atan2``) costs several times a
#: pinhole's, and a far tile is mostly out of view or behind the surface.
_SPLIT_KINDS = (SPHERICAL, CYLINDRICAL)


@functools.cache
def _integrate_kernel(kind: int, shape: int, parts: bool = True):
    """The fusion kernel compiled for one sensor kind and certainty shape (``parts=False``:
    every partial tile voxel by voxel, the reference the tests compare the parts with).

    ``kind`` and ``shape`` are closure constants, so the compiler drops every branch of
    the other models from the innermost loop (about 4x faster than one kernel that tests
    them per voxel).

    A tile is fused in passes that each do one kind of work, so that the compiler can
    vectorise the ones that are plain arithmetic (``error_model="numpy"``: a division by
    zero gives inf or NaN instead of raising, which would stop the vectoriser):

    1. per slab of ``T x T`` voxels (one value of the first index), project every voxel
       and find its quad, in one vectorised loop over the slab whose ``y`` and ``z`` come
       from per-tile tables (loops over lines of ``T`` voxels spend as much in setting up
       as in working: the slab loop made the kernel 12-14% faster);
    2. over the slab, read the quad's bounds (:func:`engine._sampling.quad_bounds`): free
       space takes ``logit(rho)`` at once, points beyond the reach nothing; the rest, the
       band, is queued with its pixel coordinates and distance;
    3. over the tile's queue: the bilinear range, then the certainty (vectorised), then
       the additions. Pass 2 prefetches each queued point's range-map corners
       (:func:`engine._sampling.prefetch_quad`), so that pass 3 finds them in cache.

    Each slab also prefetches the next slab's voxels (a slab starts at a new 2 KB of the
    tile, where the hardware prefetcher has not caught up yet).

    A queued point's quad is valid (an invalid quad's reach is ``-inf``), so pass 3 needs
    none of :func:`engine._sampling.sample_range`'s tests: it gives the same values.
    """
    linear = shape == SHAPE_LINEAR
    split = parts and kind in _SPLIT_KINDS
    sub_parts = kind == SPHERICAL  # its part test is tight enough to pay for a second level

    @njit(cache=True, parallel=True, error_model="numpy")
    def integrate(
        keys, data, rows, free, sign, T, h, M, c, params, table, rng, bounds, eps0, eps1, rho,
        falloff, q_rho, informed, o_W, p_free, p_reach, p_levels, reach_max,
    ):  # fmt: skip
        # Add ``sign`` times one scan's contribution to the tiles ``data[rows]``;
        # ``informed[row]`` receives the number of voxels of each tile the scan informs.
        # A tile with ``free[n]`` is known to be free space throughout (classify_tiles):
        # every voxel receives logit(rho), exactly what the voxel loop would add.
        free_value = sign * pack(q_rho)
        flat_bounds = bounds.reshape(-1)
        N = T * T * T
        nqv = int(params[P_H]) - 1
        nqu = quad_columns(kind, params)
        tans = row_tangents(params, table) if kind == SPHERICAL else np.empty(0)
        # band voxels decided from their row's chord where sure (engine._parts._band_outcome:
        # its monotonicity needs 0 <= eps1 < 1)
        use_chords = tans.shape[0] > 1 and 0.0 <= eps1 < 1.0
        chords = row_chords(params, table, tans) if use_chords else np.empty((2, 0))
        fit = np.array([eps0, eps1, falloff])
        # a tilted pose's voxels find their quad column from their direction where sure
        edges = column_edges(params) if kind == SPHERICAL else np.empty((2, 0))
        level = M[0, 2] == 0.0 and M[1, 2] == 0.0  # no roll or pitch
        for n in prange(rows.shape[0]):
            row = rows[n]
            tile = data[row].reshape(-1)
            if free[n]:
                for i in range(N):
                    tile[i] += free_value
                informed[row] = N
                continue
            # one slab's projections, then the tile's queue of band points
            TT = T * T
            at = np.empty(N, np.int64)
            band_u = np.empty(N)
            band_v = np.empty(N)
            band_d = np.empty(N)
            band_r = np.empty(N)
            band_q = np.empty(N, np.int64)
            count = 0
            queued = 0
            i0 = keys[row, 0] * T
            j0 = keys[row, 1] * T
            k0 = keys[row, 2] * T
            if split and T % 2 == 0:
                # eight parts of S^3 voxels, each tested as a tile first: a part out of view
                # (or behind the surface beyond the reach) is skipped, a part free throughout
                # takes logit(rho) at once; a spherical sensor's other parts are tested again
                # in eight sub-parts; the blocks left are projected voxel by voxel
                S = T // 2
                SS = S * S
                slab_y = np.empty(SS)
                slab_z = np.empty(SS)
                slab_u = np.empty(SS)
                slab_v = np.empty(SS)
                slab_d = np.empty(SS)
                slab_q = np.empty(SS, np.int64)
                part_key = np.empty(3, np.int64)
                sub_key = np.empty(3, np.int64)
                lo = np.empty(3)
                hi = np.empty(3)
                acc = np.empty(3)
                blocks = np.empty((64, 5), np.int64)  # first voxel (i, j, k), side, tile index
                nblocks = 0
                # the tile's columns of a level spherical sensor, computed once each
                # (engine._parts.level_column)
                cols = np.empty((3, TT if kind == SPHERICAL and level else 0))
                cols[0] = COL_UNKNOWN
                for part in range(8):
                    sa = (part >> 2) & 1
                    sb = (part >> 1) & 1
                    sc = part & 1
                    part_key[0] = keys[row, 0] * 2 + sa
                    part_key[1] = keys[row, 1] * 2 + sb
                    part_key[2] = keys[row, 2] * 2 + sc
                    seen = _see_part(
                        kind, part_key, S, h, M, c, o_W, params, table, flat_bounds, p_reach,
                        p_free, p_levels, reach_max, nqu, nqv, linear, lo, hi, acc,
                    )  # fmt: skip
                    if seen == OUT:
                        continue
                    corner = sa * S * TT + sb * S * T + sc * S
                    if seen == FREE:
                        _add_block(tile, corner, S, T, free_value)
                        count += S * SS
                        continue
                    if not (sub_parts and S % 2 == 0):
                        nblocks = _push(
                            blocks, nblocks, i0 + sa * S, j0 + sb * S, k0 + sc * S, S, corner
                        )
                        continue
                    R = S // 2
                    for sub in range(8):
                        ta = (sub >> 2) & 1
                        tb = (sub >> 1) & 1
                        tc = sub & 1
                        sub_key[0] = part_key[0] * 2 + ta
                        sub_key[1] = part_key[1] * 2 + tb
                        sub_key[2] = part_key[2] * 2 + tc
                        seen = _see_part(
                            kind, sub_key, R, h, M, c, o_W, params, table, flat_bounds,
                            p_reach, p_free, p_levels, reach_max, nqu, nqv, linear, lo, hi, acc,
                        )  # fmt: skip
                        if seen == OUT:
                            continue
                        inner = corner + ta * R * TT + tb * R * T + tc * R
                        if seen == FREE:
                            _add_block(tile, inner, R, T, free_value)
                            count += R * R * R
                            continue
                        nblocks = _push(
                            blocks, nblocks, i0 + sa * S + ta * R, j0 + sb * S + tb * R,
                            k0 + sc * S + tc * R, R, inner,
                        )  # fmt: skip
                for n_block in range(nblocks):
                    count, queued = _fuse_block(
                        kind, linear, tile, blocks[n_block], T, h, M, c, params, table, tans,
                        chords, fit, edges, flat_bounds, rng, free_value, at, band_u, band_v,
                        band_d, slab_y, slab_z, slab_u, slab_v, slab_d, slab_q, cols, count,
                        queued,
                    )  # fmt: skip
            else:
                slab_y = np.empty(TT)
                slab_z = np.empty(TT)
                slab_u = np.empty(TT)
                slab_v = np.empty(TT)
                slab_d = np.empty(TT)
                slab_q = np.empty(TT, np.int64)
                for b in range(T):
                    y = ((j0 + b) + 0.5) * h
                    for cc in range(T):
                        slab_y[b * T + cc] = y
                        slab_z[b * T + cc] = ((k0 + cc) + 0.5) * h
                for a in range(T):
                    x = ((i0 + a) + 0.5) * h
                    if a + 1 < T:  # the next slab's voxels, one prefetch per cache line
                        following = data[row, a + 1]
                        for first in range(0, TT, _LINE_VOXELS):
                            prefetch(following, first // T, first % T)
                    for m in range(TT):  # pass 1
                        y = slab_y[m]
                        z = slab_z[m]
                        bx = M[0, 0] * x + M[0, 1] * y + c[0]
                        by = M[1, 0] * x + M[1, 1] * y + c[1]
                        bz = M[2, 0] * x + M[2, 1] * y + c[2]
                        u, v, d = project_point(
                            kind, params, table, bx + M[0, 2] * z, by + M[1, 2] * z,
                            bz + M[2, 2] * z,
                        )  # fmt: skip
                        slab_u[m] = u
                        slab_v[m] = v
                        slab_d[m] = d
                        slab_q[m] = quad_index(kind, params, u, v)
                    base = a * TT
                    for m in range(TT):  # pass 2
                        q = slab_q[m]
                        if q < 0:
                            continue
                        d = slab_d[m]
                        if linear and d < flat_bounds[2 * q]:
                            tile[base + m] += free_value
                            count += 1
                        elif d <= flat_bounds[2 * q + 1]:
                            u = slab_u[m]
                            v = slab_v[m]
                            at[queued] = base + m
                            band_u[queued] = u
                            band_v[queued] = v
                            band_d[queued] = d
                            queued += 1
                            prefetch_quad(kind, params, rng, u, v)  # pass 3 reads its corners
            for m in range(queued):  # pass 3
                u = band_u[m]
                v = band_v[m]
                qu, qv = quad_origin(kind, params, u, v)
                band_r[m] = bilinear(rng, qu, qv, u, v)
            for m in range(queued):  # vectorised: logit is plain arithmetic
                r = band_r[m]
                value, inf = contribution(band_d[m] - r, r, eps0, eps1, rho, falloff, shape, q_rho)
                band_q[m] = sign * pack(value) if inf else 0
            for m in range(queued):
                if band_q[m] != 0:  # a packed contribution is never 0: its count bit is set
                    tile[at[m]] += band_q[m]
                    count += 1
            informed[row] = count

    return integrate


def integrate_tiles(
    scan: PreparedScan,
    grid: GridSpec,
    keys: np.ndarray,
    data: np.ndarray,
    rows: np.ndarray | None = None,
    sign: int = 1,
) -> np.ndarray:
    """Add (``sign=1``) or subtract (``sign=-1``) one scan's contribution to tiles, in place.

    Tiles out of the scan's view are skipped; tiles it sees as free space throughout take a
    constant (see :func:`engine.classify.classify_tiles`); the others are fused voxel by voxel.

    Parameters
    ----------
    scan : PreparedScan
    grid : GridSpec
    keys : int64 (n, 3)
        Tile keys.
    data : int64 (n, T, T, T)
        Packed voxels of those tiles, C-contiguous; updated in place.
    rows : int64 (m,), optional
        Only these rows of ``keys``/``data`` (default: all).

    Returns
    -------
    int64 (n,)
        Voxels informed per tile (0 for rows not processed).
    """
    keys = np.ascontiguousarray(keys, np.int64)
    rows = np.arange(len(keys), dtype=np.int64) if rows is None else np.asarray(rows, np.int64)
    status = classify_tiles(scan, grid, keys[rows])
    seen = status != OUT
    return integrate_seen(scan, grid, keys, data, rows[seen], status[seen] == FREE, sign)


def integrate_seen(
    scan: PreparedScan,
    grid: GridSpec,
    keys: np.ndarray,
    data: np.ndarray,
    rows: np.ndarray,
    free: np.ndarray,
    sign: int,
    scratch: Scratch | None = None,
    bounds: np.ndarray | None = None,
    parts: bool = True,
) -> np.ndarray:
    """:func:`integrate_tiles` on rows already classified by :func:`classify_tiles` as in
    view (``free[n]``: the scan sees row ``rows[n]`` as free space throughout). ``bounds``:
    the scan's :meth:`~engine.scans.PreparedScan.quad_bounds` if the caller has them, else
    they are computed (in ``scratch``'s array when given; see :mod:`engine._memory`).
    ``parts=False`` fuses a LiDAR's partial tiles voxel by voxel, without the tests of their
    parts: the same bits, slower (the tests' reference)."""
    informed = np.zeros(len(keys), np.int64)
    if len(rows):
        warn_if_slow_threading()
        kernel = _integrate_kernel(scan.kind, scan.shape, parts)
        if bounds is None:
            bounds = scan.quad_bounds(scratch)  # and the pyramid, when it is not there yet
        p_free, p_reach, p_levels = scan.pyramid()
        kernel(
            keys, data, np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(free),
            np.int64(sign), grid.tile_size, grid.voxel_size, scan.M, scan.c, scan.params,
            scan.table, scan.range_m, bounds, scan.eps, scan.eps_per_m, scan.rho,
            scan.falloff, scan.q_rho, informed, scan.origin_W, p_free, p_reach, p_levels,
            scan.reach_max,
        )  # fmt: skip
    return informed


@dataclass
class IntegrationReport:
    """What one change to the volume did (DESIGN.md invariant 7: meshing redoes only this)."""

    changed: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    created: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    deleted: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    voxel_updates: int = 0
    scans: int = 0


class Volume:
    """A fused volume: tiles in a store plus the scans fused into it.

    Parameters
    ----------
    grid : GridSpec
    params : FusionParams
    store : TileStore, optional
        Defaults to a :class:`MemoryTileStore`.
    """

    def __init__(self, grid: GridSpec, params: FusionParams, store: TileStore | None = None):
        self.grid = grid
        self.params = params
        self.store: TileStore = store if store is not None else MemoryTileStore(grid.tile_size)
        if self.store.tile_size != grid.tile_size:
            raise InvalidInputError("tile_size", "store and grid disagree on the tile size")
        self._scans: dict[str, Scan] = {}
        self._prepared: dict[str, PreparedScan] = {}
        self._spheres: dict[str, Sphere] = {}
        self._near = SphereIndex()  # the fused scans' spheres, for the backfill's search

    # --- scans --------------------------------------------------------------------------------
    @property
    def scan_ids(self) -> list[str]:
        return list(self._scans)

    def __contains__(self, scan_id: str) -> bool:
        return scan_id in self._scans

    def _prepare(self, scan_id: str) -> PreparedScan:
        prepared = self._prepared.get(scan_id)
        if prepared is None:
            prepared = prepare_scan(self._scans[scan_id], self.params)
            self._prepared[scan_id] = prepared
        return prepared

    # --- changes ------------------------------------------------------------------------------
    def add(self, scan_id: str, scan: Scan) -> IntegrationReport:
        """Fuse one scan; see :meth:`add_many`."""
        return self.add_many([(scan_id, scan)])

    def add_many(
        self, items: Iterable[tuple[str, Scan]], progress: Progress | None = None
    ) -> IntegrationReport:
        """Fuse scans into the volume.

        The result is bit-identical to fusing all scans the volume holds at once, in any
        order: tiles the new scans create also receive every earlier scan that has them in
        view, and the new scans update every existing tile they have in view.

        ``progress(done, total)`` is called after each scan is integrated.
        """
        items = list(items)
        new_ids: list[str] = []
        for scan_id, scan in items:
            if not isinstance(scan_id, str) or not scan_id:
                raise InvalidInputError("scan_id", f"must be a non-empty string, got {scan_id!r}")
            if scan_id in self._scans or scan_id in new_ids:
                raise InvalidInputError("scan_id", f"{scan_id!r} is already in the volume")
            if not isinstance(scan, Scan):
                raise InvalidInputError("scan", f"must be a Scan, got {type(scan).__name__}")
            new_ids.append(scan_id)
        for scan_id, scan in items:
            self._scans[scan_id] = scan
        try:
            report = self._integrate_new(new_ids, progress)
        except BaseException:
            for scan_id in new_ids:
                self._scans.pop(scan_id, None)
                self._prepared.pop(scan_id, None)
                self._spheres.pop(scan_id, None)
            raise
        for scan_id in new_ids:
            sphere = self._sphere(scan_id)
            self._near.add(scan_id, sphere.origin, sphere.radius_m)
        return report

    def _sphere(self, scan_id: str) -> Sphere:
        sphere = self._spheres.get(scan_id)
        if sphere is None:
            prepared = self._prepare(scan_id)
            origin = tuple(float(x) for x in prepared.origin_W)
            sphere = Sphere(scan_id, origin, reach_radius(prepared))  # type: ignore[arg-type]
            self._spheres[scan_id] = sphere
        return sphere

    def _integrate_new(self, new_ids: list[str], progress: Progress | None) -> IntegrationReport:
        # the plan (engine.planner): allocate, then each scan into the tiles it has in view;
        # the earlier scans near the created tiles come from the index of their spheres
        scratch = Scratch()  # working arrays, reused from scan to scan
        plan = plan_add(
            self.grid, self.store.keys(), new_ids, self._near, self._prepare, scratch=scratch
        )
        keys, created = plan.keys, plan.created
        T = self.grid.tile_size
        data = zeros((len(keys), T, T, T), np.int64)  # ordinary pages: see engine._memory
        loaded = created.copy()  # created tiles start from unknown
        changed = np.zeros(len(keys), np.bool_)
        updates = 0
        for view in plan.views(self._prepare, scratch):
            self._load_rows(keys, data, loaded, view.rows)
            informed = integrate_seen(
                self._prepare(view.scan_id), self.grid, keys, data, view.rows, view.free,
                view.sign, scratch, view.bounds,
            )  # fmt: skip
            changed |= informed > 0
            updates += int(informed.sum())
            if progress is not None and view.step < len(new_ids):
                progress(view.step + 1, len(new_ids))
        # write what changed, was created or changes owners
        write = changed | created
        write[plan.owned_rows()] = True
        rows = np.flatnonzero(write)
        self._load_rows(keys, data, loaded, rows)  # owner changes on tiles not in view
        owners = plan.owners_after(rows, self.store.owners(keys[rows]))
        written = data if len(rows) == len(keys) else data[rows]  # no copy in the usual case
        # the batch is not used again: a memory store may keep it rather than copy it
        self.store.write(keys[rows], written, owners, take=True)
        return IntegrationReport(
            changed=keys[changed], created=plan.created_keys(), voxel_updates=updates,
            scans=len(new_ids),
        )  # fmt: skip

    def _load_rows(
        self, keys: np.ndarray, data: np.ndarray, loaded: np.ndarray, rows: np.ndarray
    ) -> None:
        """Read the tiles ``rows`` of ``keys`` into ``data`` unless they are there already."""
        todo = rows[~loaded[rows]]
        if len(todo):
            data[todo] = self.store.read(keys[todo])
            loaded[todo] = True

    def remove(self, scan_id: str) -> IntegrationReport:
        """Remove a scan: subtract exactly its contribution; drop tiles it alone owned.

        Restores, bit for bit, the volume fused without the scan.
        """
        if scan_id not in self._scans:
            raise ScanNotFoundError(f"scan {scan_id!r} is not in the volume")
        plan = plan_remove(self.grid, self._sphere(scan_id), self.store.keys(), self.store.owners)
        keys = plan.keys
        in_view = next(plan.views(self._prepare), None)  # one step: the scan
        # the tiles it is subtracted from, and those it no longer owns
        seen = in_view.rows if in_view is not None else keys[:0, 0]
        rows = np.union1d(seen, plan.owned_rows())
        data = self.store.read(keys[rows])
        informed = np.zeros(len(rows), np.int64)
        if in_view is not None:
            informed = integrate_seen(
                self._prepare(scan_id), self.grid, keys[rows], data,
                np.searchsorted(rows, in_view.rows), in_view.free, in_view.sign,
            )  # fmt: skip
        self.store.write(keys[rows], data, plan.owners_after(rows, self.store.owners(keys[rows])))
        self.store.delete(plan.deleted)
        del self._scans[scan_id]
        self._prepared.pop(scan_id, None)
        self._spheres.pop(scan_id, None)
        self._near.remove(scan_id)
        return IntegrationReport(
            changed=keys[rows][informed > 0], deleted=plan.deleted,
            voxel_updates=int(informed.sum()), scans=1,
        )  # fmt: skip

    # --- reading ------------------------------------------------------------------------------
    def tile_keys(self) -> np.ndarray:
        return self.store.keys()

    def extract_mesh(self, *, refine: bool = True, bounds: Sequence[float] | None = None) -> Mesh:
        """The surface of the volume as one mesh (see :func:`engine.meshing.mesh_tiles`)."""
        scans = [self._prepare(scan_id) for scan_id in self._scans]
        return extract_mesh(self.store, self.grid, self.params, scans, refine=refine, bounds=bounds)

    def to_dense(self, bounds: Sequence[float] | None = None) -> DenseGrid:
        """The fused log-odds as a dense grid (see :func:`engine.volume.dense_logodds`)."""
        return dense_logodds(self.store, self.grid, bounds)
