"""Surface extraction: per-tile marching cubes, edge refinement, exact stitching.

METHOD.md §3, DESIGN.md invariants 6-7; the design is in ``docs/meshing.md``.

The surface is the level ``L = 0`` of the fused log-odds; a voxel is *inside*
(occupied) when ``L > 0``. Cube ``v`` spans voxels ``v .. v + 1`` on each axis
and belongs to the tile holding ``v``, so each tile meshes its own cubes and
reads a one-voxel halo from its upper neighbours. A vertex is keyed by its cube
edge: the global index of the edge's lower voxel and the edge's axis. Its
position depends only on that edge and the scans (linear interpolation of the
two voxels' integer log-odds or, with refinement, the crossing of the fused
certainty re-evaluated from the range maps along the edge, summed as the same
quantised integers the volume holds), so every tile that has the edge produces
the same vertex, and stitching is a merge by key.

Unknown voxels: *mapping* makes no faces in cubes that touch an unknown voxel
or leave the region of interest (open surfaces); *closed* counts unknown voxels
of the region as occupied (the value of one scan's ``logit(1 - rho)``) and
voxels outside it as free, so the mesh is closed. Faces of cubes with such a
substituted corner are *inferred*; the others are *observed*.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ._mc_tables import EDGE_AXIS, EDGE_CORNER, TRI_COUNT, TRI_TABLE
from ._refine import edge_crossings, refine_edges
from .certainty import logit, quantise
from .defaults import COUNT_BITS, REFINE_SAMPLES
from .errors import InvalidGridError
from .grid import Bounds, GridSpec, pack_keys, unique_keys
from .scans import FusionParams, PreparedScan
from .volume import TileReader

__all__ = [
    "HALO_TILES",
    "Mesh",
    "TileMeshes",
    "extract_mesh",
    "mesh_region",
    "mesh_tiles",
    "stitch",
    "tiles_to_mesh",
]

_COUNT_MASK = (1 << COUNT_BITS) - 1
_FAR = 1 << 40  # voxel index bound of "no region of interest"
#: Refuse to consider more tiles than this in closed mode (the region of interest is dense).
_MAX_CLOSED_TILES = 4_000_000


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in world metres.

    ``faces`` wind counter-clockwise seen from outside (normals point from occupied into
    free space). ``inferred[f]`` is True for faces that lie against unknown space or the
    boundary of the region of interest (closed mode). ``vertex_keys[v]`` is the cube edge
    of vertex ``v``: the global voxel index ``(i, j, k)`` of its lower end and its axis.
    """

    vertices: np.ndarray  # float64 (n, 3)
    faces: np.ndarray  # int64 (m, 3)
    inferred: np.ndarray  # bool (m,)
    vertex_keys: np.ndarray  # int64 (n, 4)

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


@dataclass(frozen=True, eq=False)
class TileMeshes:
    """The meshes of several tiles, concatenated (before stitching).

    Tile ``n`` owns vertices ``vertex_offsets[n] : vertex_offsets[n + 1]`` and faces
    ``face_offsets[n] : face_offsets[n + 1]``; ``faces`` index the concatenated vertices.
    An edge on a face between two tiles appears in both, with the same position.
    """

    keys: np.ndarray  # int64 (t, 3): tile keys
    vertex_offsets: np.ndarray  # int64 (t + 1,)
    face_offsets: np.ndarray  # int64 (t + 1,)
    vertex_keys: np.ndarray  # int64 (n, 4)
    vertices: np.ndarray  # float64 (n, 3)
    faces: np.ndarray  # int64 (m, 3)
    inferred: np.ndarray  # bool (m,)


# --------------------------------------------------------------------------------------------
# marching cubes over tiles (count, then fill)


_INSIDE = 1  # voxel bits in a block
_UNUSABLE = 2  # unknown (mapping mode): cubes touching it make no faces
_SUBST = 4  # unknown or outside the region, given a value (closed mode): faces are inferred
_NO_CASE = -1


@njit(cache=True)
def _fill_block(n, keys, nb, data, T, roi_lo, roi_hi, closed, u_in, u_out, L, bits):
    """Decode tile ``n`` and its upper halo into ``L`` (log-odds) and ``bits``."""
    for a in range(T + 1):
        da = 1 if a == T else 0
        ia = a - T * da
        gi = keys[n, 0] * T + a
        in_a = roi_lo[0] <= gi < roi_hi[0]
        for b in range(T + 1):
            db = 1 if b == T else 0
            ib = b - T * db
            gj = keys[n, 1] * T + b
            in_ab = in_a and roi_lo[1] <= gj < roi_hi[1]
            for c in range(T + 1):
                dc = 1 if c == T else 0
                ic = c - T * dc
                gk = keys[n, 2] * T + c
                row = nb[n, da + 2 * db + 4 * dc]
                packed = data[row, ia, ib, ic] if row >= 0 else np.int64(0)
                value = np.int64(0)
                flag = 0
                if not (in_ab and roi_lo[2] <= gk < roi_hi[2]):
                    value = u_out
                    flag = _SUBST if closed else _UNUSABLE
                elif packed & _COUNT_MASK == 0:
                    value = u_in
                    flag = _SUBST if closed else _UNUSABLE
                else:
                    value = packed >> COUNT_BITS
                L[a, b, c] = value
                bits[a, b, c] = flag | (_INSIDE if value > 0 else 0)


@njit(cache=True)
def _cases(T, bits, cases):
    """Marching-cubes case of every cube of a block (``_NO_CASE`` if it touches an unusable
    voxel; ``+256`` when a corner is substituted); returns the number of cubes with faces."""
    active = 0
    for a in range(T):
        for b in range(T):
            prev = (
                bits[a, b, 0]
                | (bits[a + 1, b, 0] << 3)
                | (bits[a, b + 1, 0] << 6)
                | (bits[a + 1, b + 1, 0] << 9)
            )
            for c in range(T):
                cur = (
                    bits[a, b, c + 1]
                    | (bits[a + 1, b, c + 1] << 3)
                    | (bits[a, b + 1, c + 1] << 6)
                    | (bits[a + 1, b + 1, c + 1] << 9)
                )
                both = prev | cur
                if both & 0o2222:  # an unusable corner
                    cases[a, b, c] = _NO_CASE
                else:
                    case = (
                        (prev & 1)
                        | ((prev >> 3) & 1) << 1
                        | ((prev >> 6) & 1) << 2
                        | ((prev >> 9) & 1) << 3
                        | (cur & 1) << 4
                        | ((cur >> 3) & 1) << 5
                        | ((cur >> 6) & 1) << 6
                        | ((cur >> 9) & 1) << 7
                    )
                    if case == 0 or case == 255:
                        cases[a, b, c] = _NO_CASE
                    else:
                        if both & 0o4444:
                            case += 256
                        cases[a, b, c] = case
                        active += 1
                prev = cur
    return active


@njit(cache=True, inline="always")
def _local_edge(T, a, b, c, e, edge_corner, edge_axis):
    n1 = T + 1
    return (
        ((a + edge_corner[e, 0]) * n1 + (b + edge_corner[e, 1])) * n1 + (c + edge_corner[e, 2])
    ) * 3 + edge_axis[e]


@njit(cache=True, parallel=True)
def _count(
    keys,
    nb,
    data,
    T,
    roi_lo,
    roi_hi,
    closed,
    u_in,
    u_out,
    tri_count,
    tri_table,
    edge_corner,
    edge_axis,
    n_tris,
    n_verts,
):
    n1 = T + 1
    for n in prange(keys.shape[0]):
        L = np.empty((n1, n1, n1), np.int64)
        bits = np.empty((n1, n1, n1), np.int64)
        cases = np.empty((T, T, T), np.int16)
        _fill_block(n, keys, nb, data, T, roi_lo, roi_hi, closed, u_in, u_out, L, bits)
        n_tris[n] = 0
        n_verts[n] = 0
        if _cases(T, bits, cases) == 0:
            continue
        mark = np.zeros(n1 * n1 * n1 * 3, np.bool_)
        tris = 0
        verts = 0
        for a in range(T):
            for b in range(T):
                for c in range(T):
                    case = cases[a, b, c]
                    if case == _NO_CASE:
                        continue
                    case &= 255
                    m = tri_count[case]
                    tris += m
                    for e3 in range(3 * m):
                        le = _local_edge(T, a, b, c, tri_table[case, e3], edge_corner, edge_axis)
                        if not mark[le]:
                            mark[le] = True
                            verts += 1
        n_tris[n] = tris
        n_verts[n] = verts


@njit(cache=True, parallel=True)
def _fill(
    keys,
    nb,
    data,
    T,
    roi_lo,
    roi_hi,
    closed,
    u_in,
    u_out,
    tri_count,
    tri_table,
    edge_corner,
    edge_axis,
    v_off,
    f_off,
    vkey,
    vlo,
    vhi,
    vknown,
    faces,
    inferred,
):
    n1 = T + 1
    for n in prange(keys.shape[0]):
        if f_off[n + 1] == f_off[n]:
            continue
        L = np.empty((n1, n1, n1), np.int64)
        bits = np.empty((n1, n1, n1), np.int64)
        cases = np.empty((T, T, T), np.int16)
        _fill_block(n, keys, nb, data, T, roi_lo, roi_hi, closed, u_in, u_out, L, bits)
        _cases(T, bits, cases)
        vid = np.full(n1 * n1 * n1 * 3, -1, np.int64)
        nv = v_off[n]
        nf = f_off[n]
        # vertices numbered in order of first use, faces in cube order: deterministic
        for a in range(T):
            for b in range(T):
                for c in range(T):
                    case = cases[a, b, c]
                    if case == _NO_CASE:
                        continue
                    inf = case >= 256
                    case &= 255
                    for t in range(tri_count[case]):
                        for j in range(3):
                            e = tri_table[case, 3 * t + j]
                            le = _local_edge(T, a, b, c, e, edge_corner, edge_axis)
                            if vid[le] < 0:
                                vid[le] = nv
                                axis = edge_axis[e]
                                a1 = a + edge_corner[e, 0]
                                b1 = b + edge_corner[e, 1]
                                c1 = c + edge_corner[e, 2]
                                a2 = a1 + (1 if axis == 0 else 0)
                                b2 = b1 + (1 if axis == 1 else 0)
                                c2 = c1 + (1 if axis == 2 else 0)
                                vkey[nv, 0] = keys[n, 0] * T + a1
                                vkey[nv, 1] = keys[n, 1] * T + b1
                                vkey[nv, 2] = keys[n, 2] * T + c1
                                vkey[nv, 3] = axis
                                vlo[nv] = L[a1, b1, c1]
                                vhi[nv] = L[a2, b2, c2]
                                vknown[nv] = (bits[a1, b1, c1] | bits[a2, b2, c2]) & _SUBST == 0
                                nv += 1
                            faces[nf, j] = vid[le]
                        inferred[nf] = inf
                        nf += 1


# --------------------------------------------------------------------------------------------
# which tiles, and their data


def mesh_region(grid: GridSpec, bounds: Sequence[float] | None) -> tuple[np.ndarray, np.ndarray]:
    if bounds is not None:
        box: Bounds = tuple(float(x) for x in bounds)  # type: ignore[assignment]
        return GridSpec(grid.voxel_size, grid.tile_size, "mapping", box).roi_voxels()
    if grid.bounds is not None:
        return grid.roi_voxels()
    return np.full(3, -_FAR, np.int64), np.full(3, _FAR, np.int64)


#: A tile and the 7 tiles its cubes' one-voxel halo reads: offset ``d`` is
#: ``(d & 1, d >> 1 & 1, d >> 2 & 1)``. The storage invalidates cached tile meshes with it.
HALO_TILES = np.array([[d & 1, (d >> 1) & 1, (d >> 2) & 1] for d in range(8)], np.int64)


def tiles_to_mesh(
    existing: np.ndarray, grid: GridSpec, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Tiles whose cubes may hold faces."""
    T = grid.tile_size
    # cubes with a corner in the region: lowest corner in [lo - 1, hi - 1]
    t_lo = np.floor_divide(lo - 1, T)
    t_hi = np.floor_divide(hi - 1, T)
    if grid.mode == "mapping":
        keys = existing
        if len(keys):
            keys = keys[np.all((keys >= t_lo) & (keys <= t_hi), axis=1)]
        return keys
    # closed: tiles next to an existing tile, and tiles on the region's boundary
    near = unique_keys(
        np.concatenate([np.zeros((0, 3), np.int64)] + [existing - d for d in HALO_TILES])
    )
    near = near[np.all((near >= t_lo) & (near <= t_hi), axis=1)]
    n_tiles = int(np.prod(t_hi - t_lo + 1))
    if n_tiles > _MAX_CLOSED_TILES:
        raise InvalidGridError(
            "bounds", f"closed-mode meshing of {n_tiles} tiles is too large; give smaller bounds"
        )
    shell = []
    for axis in range(3):
        for side in (t_lo[axis], t_hi[axis]):
            ranges = [np.arange(t_lo[a], t_hi[a] + 1) for a in range(3)]
            ranges[axis] = np.array([side])
            grids = np.meshgrid(*ranges, indexing="ij")
            shell.append(np.stack([g.ravel() for g in grids], axis=1))
    return unique_keys(np.concatenate([near, *shell]).astype(np.int64))


def _neighbour_rows(mesh_keys: np.ndarray, data_keys: np.ndarray) -> np.ndarray:
    """Row in ``data_keys`` of each mesh tile's 8 blocks (itself and its upper neighbours)."""
    nb = np.full((len(mesh_keys), 8), -1, np.int64)
    if len(data_keys) == 0:
        return nb
    packed = pack_keys(data_keys)
    for d, off in enumerate(HALO_TILES):
        want = pack_keys(mesh_keys + off)
        pos = np.minimum(np.searchsorted(packed, want), len(packed) - 1)
        nb[:, d] = np.where(packed[pos] == want, pos, -1)
    return nb


# --------------------------------------------------------------------------------------------
# public API


def mesh_tiles(
    store: TileReader,
    grid: GridSpec,
    params: FusionParams,
    scans: Iterable[PreparedScan],
    keys: np.ndarray | None = None,
    *,
    refine: bool = True,
    bounds: Sequence[float] | None = None,
    n_samples: int = REFINE_SAMPLES,
) -> TileMeshes:
    """Mesh tiles on their own (marching cubes with a one-voxel halo, edge refinement).

    Parameters
    ----------
    store, grid, params
        The fused volume and its fusion parameters (closed mode gives unknown voxels the
        value of one scan's ``logit(1 - rho)``, voxels outside the region ``logit(rho)``).
    scans : iterable of PreparedScan
        Every scan fused into the volume that may inform these tiles (edge refinement
        re-evaluates them, iterating once; unused without ``refine``).
    keys : int64 (t, 3), optional
        The tiles to mesh (default: every tile that may hold faces).
    refine : bool
        Place vertices at the crossing of the certainty re-evaluated from the range maps
        at ``n_samples - 1`` points along each edge (METHOD.md §3) instead of linear
        interpolation of the two voxels' log-odds.
    bounds : (x0, y0, z0, x1, y1, z1), optional
        Mesh only this box (default: the grid's region of interest, if any).
    """
    T = grid.tile_size
    closed = grid.mode == "closed"
    lo, hi = mesh_region(grid, bounds)
    existing = store.keys()
    if keys is None:
        keys = tiles_to_mesh(existing, grid, lo, hi)
    keys = unique_keys(np.asarray(keys, np.int64).reshape(-1, 3))
    wanted = unique_keys(
        np.concatenate([np.zeros((0, 3), np.int64)] + [keys + d for d in HALO_TILES])
    )
    data_keys = (
        wanted[np.isin(pack_keys(wanted), pack_keys(existing))] if len(existing) else wanted[:0]
    )
    data = store.read(data_keys) if len(data_keys) else np.zeros((1, T, T, T), np.int64)
    nb = _neighbour_rows(keys, data_keys)
    q_rho = int(quantise(logit(params.noise.rho)))  # < 0
    u_in, u_out = np.int64(-q_rho), np.int64(q_rho)
    tables = (TRI_COUNT, TRI_TABLE, EDGE_CORNER, EDGE_AXIS)
    n_tris = np.zeros(len(keys), np.int64)
    n_verts = np.zeros(len(keys), np.int64)
    if len(keys):
        _count(keys, nb, data, T, lo, hi, closed, u_in, u_out, *tables, n_tris, n_verts)
    v_off = np.concatenate([[0], np.cumsum(n_verts)]).astype(np.int64)
    f_off = np.concatenate([[0], np.cumsum(n_tris)]).astype(np.int64)
    nv, nf = int(v_off[-1]), int(f_off[-1])
    vkey = np.empty((nv, 4), np.int64)
    vlo = np.empty(nv, np.int64)
    vhi = np.empty(nv, np.int64)
    vknown = np.empty(nv, np.bool_)
    faces = np.empty((nf, 3), np.int64)
    inferred = np.empty(nf, np.bool_)
    if len(keys):
        _fill(
            keys, nb, data, T, lo, hi, closed, u_in, u_out, *tables,
            v_off, f_off, vkey, vlo, vhi, vknown, faces, inferred,
        )  # fmt: skip
    del data
    if refine and nv:
        acc = refine_edges(keys, v_off, vkey, vknown, scans, grid, n_samples)
    else:
        acc = np.zeros((0, max(n_samples - 1, 1)), np.int64)
    t = np.empty(nv, np.float64)
    edge_crossings(vlo, vhi, vknown, acc, n_samples, t)
    h = grid.voxel_size
    vertices = (vkey[:, :3].astype(np.float64) + 0.5) * h
    vertices[np.arange(nv), vkey[:, 3]] += t * h
    return TileMeshes(
        keys=keys,
        vertex_offsets=v_off,
        face_offsets=f_off,
        vertex_keys=vkey,
        vertices=vertices,
        faces=faces,
        inferred=inferred,
    )


def stitch(parts: Sequence[TileMeshes] | TileMeshes) -> Mesh:
    """Merge tile meshes into one mesh by vertex key (exact; no float tolerance).

    The result does not depend on how the tiles were grouped into parts or in which order
    the parts come: vertices are ordered by key, faces by tile key (a tile's own faces in
    the order meshing made them), so a mesh stitched from cached tile meshes is the same
    bits as a fresh one.
    """
    if isinstance(parts, TileMeshes):
        parts = [parts]
    vkey = np.concatenate([np.zeros((0, 4), np.int64)] + [p.vertex_keys for p in parts])
    verts = np.concatenate([np.zeros((0, 3), np.float64)] + [p.vertices for p in parts])
    faces_list = []
    face_tiles = []
    base = 0
    for p in parts:
        faces_list.append(p.faces + base)
        base += len(p.vertex_keys)
        face_tiles.append(np.repeat(p.keys, np.diff(p.face_offsets), axis=0))
    faces = np.concatenate([np.zeros((0, 3), np.int64), *faces_list])
    inferred = np.concatenate([np.zeros(0, np.bool_)] + [p.inferred for p in parts])
    if len(vkey) == 0:
        return Mesh(verts, faces, inferred, vkey)
    if len(parts) > 1:  # faces by tile key, whatever the order of the parts
        order = np.argsort(pack_keys(np.concatenate(face_tiles)), kind="stable")
        faces, inferred = faces[order], inferred[order]
    packed = _pack_vertex_keys(vkey)
    _, first, inverse = np.unique(packed, return_index=True, return_inverse=True)
    return Mesh(
        vertices=verts[first],
        faces=inverse[faces].astype(np.int64),
        inferred=inferred,
        vertex_keys=vkey[first],
    )


def _pack_vertex_keys(vkey: np.ndarray) -> np.ndarray:
    """One int64 per edge key (mixed radix over the keys' extent)."""
    lo = vkey[:, :3].min(axis=0)
    ext = vkey[:, :3].max(axis=0) - lo + 1
    if float(np.prod(ext.astype(np.float64))) * 3 >= 2.0**62:
        raise InvalidGridError("bounds", "the mesh spans too many voxels to key its vertices")
    rel = vkey[:, :3] - lo
    return ((rel[:, 0] * ext[1] + rel[:, 1]) * ext[2] + rel[:, 2]) * 3 + vkey[:, 3]


def extract_mesh(
    store: TileReader,
    grid: GridSpec,
    params: FusionParams,
    scans: Iterable[PreparedScan],
    *,
    refine: bool = True,
    bounds: Sequence[float] | None = None,
    n_samples: int = REFINE_SAMPLES,
) -> Mesh:
    """The surface ``L = 0`` of a fused volume as one stitched mesh (see :func:`mesh_tiles`)."""
    return stitch(
        mesh_tiles(store, grid, params, scans, refine=refine, bounds=bounds, n_samples=n_samples)
    )
