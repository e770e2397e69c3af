"""Units of work: everything a scene computes, as plain data a runner can send anywhere
(docs/storage.md, "Units that can run again"; docs/scale-out.md).

Three kinds, each a picklable dataclass and a function of it alone, run wherever the
store's files are visible (in this process, on the workers of a Dask cluster) and never
touching the catalog, which stays with the process that orchestrates the scene:

* :class:`PlanUnit` / :func:`plan_unit`: the planner's plan of a change and its views
  (allocation and tile classification, engine.planner);
* :class:`TileUnit` / :func:`integrate_unit`: some tiles of a plan, with the scans to add or
  subtract in each. It reads the committed chunks and writes the tiles it changes to the
  scene's staging area, so a unit killed at any point and run again gives the same bits;
  the scene's checkpoint publishes the staged chunks once every unit has finished;
* :class:`MeshUnit` / :func:`mesh_unit`: the meshes of some tiles.

A :class:`Runner` runs a list of units and returns their results in order.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
from rangefuse.engine import FusionParams, GridSpec, PreparedScan, Scan, prepare_scan
from rangefuse.engine.fusion import integrate_seen
from rangefuse.engine.grid import pack_keys, unpack_keys
from rangefuse.engine.meshing import mesh_tiles
from rangefuse.engine.planner import (
    Plan,
    Sphere,
    View,
    plan_add,
    plan_rebuild,
    plan_remove,
    scans_near,
)

from ._heap import release_free_memory
from .archive import ScanArchive
from .mesh_cache import encode_tile_mesh
from .staging import Staging
from .tile_cache import TileCache
from .zarr_tiles import ZarrTiles

__all__ = [
    "InProcess",
    "MeshUnit",
    "PlanUnit",
    "Runner",
    "TileUnit",
    "UnitResult",
    "consumed_views",
    "integrate_unit",
    "make_units",
    "mesh_unit",
    "plan_unit",
    "tile_scan_rows",
]

Item = TypeVar("Item")
Result = TypeVar("Result")


#: Bytes of range maps a unit keeps as read from the archive (the planner reads each new
#: scan twice, for its allocation and for its view; a tile unit reads a scan once for each
#: batch of tiles it has in view): 256 scans of 64 x 1024.
RAW_SCAN_BYTES = 64 * 2**20


class _Scans:
    """A scene's archived scans, prepared for the kernels on first use; the last two kept
    prepared (a unit's memory is one scan or two, not the group's), and the first scans
    read from the archive kept as read, up to :data:`RAW_SCAN_BYTES` of range maps. The
    scans are drawn in the same order pass after pass (the planner's two, a unit's batches
    of tiles): keeping the first ones serves that many of each later pass from memory,
    where keeping the last ones served none once a group's scans outgrew the budget."""

    def __init__(self, group: Path, params: FusionParams) -> None:
        self.archive = ScanArchive(group)
        self.params = params
        self._prepared: OrderedDict[str, PreparedScan] = OrderedDict()
        self._raw: dict[str, Scan] = {}
        self._raw_bytes = 0

    def __call__(self, scan_id: str) -> PreparedScan:
        prepared = self._prepared.get(scan_id)
        if prepared is None:
            while len(self._prepared) > 1:  # before the next one is made: two at most
                self._prepared.popitem(last=False)
            prepared = prepare_scan(self._read(scan_id), self.params)
            self._prepared[scan_id] = prepared
        else:
            self._prepared.move_to_end(scan_id)
        return prepared

    def _read(self, scan_id: str) -> Scan:
        scan = self._raw.get(scan_id)
        if scan is not None:
            return scan
        scan = self.archive.get(scan_id)
        if self._raw_bytes + scan.range_m.nbytes <= RAW_SCAN_BYTES:
            self._raw[scan_id] = scan
            self._raw_bytes += scan.range_m.nbytes
        return scan


# --------------------------------------------------------------------------------------------
# planning


@dataclass(frozen=True)
class PlanUnit:
    """Plan a change of a scene (engine.planner) with the one-voxel halo of a scene that
    keeps tile meshes. ``kind`` is ``"add"`` (``existing``: packed keys of the tiles;
    ``scans``: the new ones; ``spheres``: the fused ones), ``"remove"`` (``existing``: the
    tiles near the scan, whose ``owners`` are given by packed key; ``spheres``: the scan's)
    or ``"rebuild"`` (``existing``: the tiles; ``informing``: rows each scan may inform)."""

    group_path: str
    grid: dict[str, Any]
    params: dict[str, Any]
    kind: str
    existing: np.ndarray
    scans: list[str] = field(default_factory=list)
    spheres: list[Sphere] = field(default_factory=list)
    owners: dict[int, frozenset[str]] = field(default_factory=dict)
    informing: dict[str, np.ndarray] = field(default_factory=dict)
    halo: int = 1
    max_pairs: int | None = None


def plan_unit(unit: PlanUnit) -> tuple[Plan, list[View]]:
    """The plan and its views (without the per-quad bounds, which stay where they were
    computed, and without its steps' candidates, which the views replace). An ``"add"``
    with ``max_pairs`` may plan only the first of its scans (``plan_add``): the keys of
    ``plan.owned``."""
    grid = GridSpec.from_dict(unit.grid)
    load = _Scans(Path(unit.group_path), FusionParams.from_dict(unit.params))
    keys = unpack_keys(np.asarray(unit.existing, np.int64))
    if unit.kind == "add":
        plan = plan_add(grid, keys, unit.scans, unit.spheres, load, halo=unit.halo,
                        max_pairs=unit.max_pairs)  # fmt: skip
    elif unit.kind == "remove":
        owners = unit.owners

        def owners_of(tiles: np.ndarray) -> list[frozenset[str]]:
            return [owners[p] for p in pack_keys(tiles).tolist()]

        (sphere,) = unit.spheres
        plan = plan_remove(grid, sphere, keys, owners_of, halo=unit.halo)
    elif unit.kind == "rebuild":
        plan = plan_rebuild(grid, keys, unit.informing, halo=unit.halo)
    else:
        raise ValueError(f"unknown kind of plan {unit.kind!r}")
    views = [replace(view, bounds=None) for view in plan.views(load)]
    # a new empty array: a slice of the candidates would keep their memory alive
    plan.steps = [replace(step, candidates=np.zeros(0, np.int64)) for step in plan.steps]
    release_free_memory()
    return plan, views


@dataclass(frozen=True)
class TileUnit:
    """Add and subtract scans in some tiles of a scene.

    ``steps`` lists ``(scan_id, rows, free, sign)``: the rows of ``keys`` the archived scan
    has in view, whether it sees each as free space throughout, and 1 to add it or -1 to
    subtract it (exact removal). ``new`` marks tiles that start from unknown instead of their
    committed chunk (created, or rebuilt). ``name`` tells the unit from the group's others
    in the staging area (``u<n>``).
    """

    group_path: str
    staging_path: str
    grid: dict[str, Any]
    params: dict[str, Any]
    keys: np.ndarray
    new: np.ndarray
    steps: list[tuple[str, np.ndarray, np.ndarray, int]]
    cache_mb: float
    name: str = "u0"


@dataclass(frozen=True)
class UnitResult:
    informed: dict[str, np.ndarray]  # rows of the unit's keys each scan informs
    voxel_updates: int
    fuse_seconds: float = 0.0  # wall time in the fusion kernel (the rest: I/O, set-up)


def integrate_unit(unit: TileUnit) -> UnitResult:
    """Carry out a unit: stage (and fsync) every tile it changes; returns what it informed.

    Tiles are the outer loop: each tile is read once and staged once, whatever the number
    of scans. A scan is prepared when a batch of tiles has it in view and not kept beyond
    the next (``_Scans``): the unit's memory is its tile cache and a scan or two, not the
    group's scans. No other unit of the group has any of the unit's tiles.
    """
    grid = GridSpec.from_dict(unit.grid)
    group = Path(unit.group_path)
    tiles = ZarrTiles.open(group)
    staging = Staging(Path(unit.staging_path), tiles, unit.name)
    load = _Scans(group, FusionParams.from_dict(unit.params))
    cache = TileCache(tiles, staging, int(unit.cache_mb * 2**20))
    steps = [_sorted_step(rows, free) for _, rows, free, _ in unit.steps]
    hits: list[list[np.ndarray]] = [[] for _ in steps]
    n = len(unit.keys)
    updates = 0
    fuse_seconds = 0.0
    for start in range(0, n, cache.batch):
        end = min(n, start + cache.batch)
        keys = unit.keys[start:end]
        data = cache.fetch(keys, unit.new[start:end])
        for k, (rows, free) in enumerate(steps):
            a, b = np.searchsorted(rows, [start, end]).tolist()
            if a == b:
                continue
            prepared = load(unit.steps[k][0])
            t0 = time.perf_counter()
            count = integrate_seen(
                prepared, grid, keys, data, rows[a:b] - start, free[a:b], unit.steps[k][3]
            )  # fmt: skip
            fuse_seconds += time.perf_counter() - t0
            hits[k].append((np.flatnonzero(count > 0) + start).astype(rows.dtype))
            updates += int(count.sum())
        cache.store(keys, data)
        del data  # the cache holds the batch's tiles now
    cache.flush()
    staging.finish()
    informed = {
        scan_id: np.concatenate([steps[k][0][:0], *hits[k]])
        for k, (scan_id, *_) in enumerate(unit.steps)
    }
    del cache, hits, load  # the tiles, the batches and the scans, before the heap is trimmed
    release_free_memory()
    return UnitResult(informed=informed, voxel_updates=updates, fuse_seconds=fuse_seconds)


def _sorted_step(rows: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A step's rows in increasing order (a batch of tiles is then a slice of them) with
    their free flags (the planner's rows are sorted already)."""
    rows = np.asarray(rows)
    free = np.asarray(free, np.bool_)
    if len(rows) > 1 and not bool(np.all(rows[1:] > rows[:-1])):
        order = np.argsort(rows, kind="stable")
        rows, free = rows[order], free[order]
    return rows, free


def make_units(
    keys: np.ndarray,
    new: np.ndarray,
    views: Iterable[View],
    n_parts: int,
    **where: Any,
) -> list[TileUnit]:
    """Split the tiles ``keys`` (with their ``new`` flags) among ``n_parts`` units by key
    (a tile always goes to the same part: one writer per tile). ``views`` index ``keys``
    (drawn once, in order; a unit's rows are int32 where its tiles allow); ``where`` gives
    the units' other fields (paths, grid, params, cache budget per unit)."""
    n_parts = max(1, min(n_parts, len(keys)))
    part_of = _partition(keys, n_parts)
    local = np.zeros(len(keys), np.int64)
    mines = [np.flatnonzero(part_of == p) for p in range(n_parts)]
    for mine in mines:
        local[mine] = np.arange(len(mine))
    row_type = np.int32 if len(keys) <= np.iinfo(np.int32).max else np.int64
    steps: list[list[tuple[str, np.ndarray, np.ndarray, int]]] = [[] for _ in mines]
    for view in views:
        parts = part_of[view.rows]
        for p in range(n_parts):
            sel = parts == p
            if sel.any():
                rows = local[view.rows[sel]].astype(row_type)
                steps[p].append((view.scan_id, rows, view.free[sel], view.sign))
    return [
        TileUnit(keys=keys[mine], new=new[mine], steps=steps[p], name=f"u{p}", **where)
        for p, mine in enumerate(mines)
    ]


def consumed_views(views: list[View], position: np.ndarray) -> Iterator[View]:
    """``views`` with their rows mapped through ``position``, each taken out of the list as
    it is drawn (a group's views are released while its units are made)."""
    views.reverse()
    while views:
        v = views.pop()
        yield View(v.scan_id, v.step, position[v.rows], v.free, v.sign)


def tile_scan_rows(
    unit_keys: Sequence[np.ndarray], results: Sequence[UnitResult], plan: Plan
) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """The catalog's rows of a group, one scan at a time (by id): the packed keys of the
    tiles the scan informs (from the units' results, which give them up as they go) or owns
    (from the plan), sorted, and whether it owns each. A group's pairs are never all
    packed at once."""
    none = np.zeros(0, np.int64)
    for scan_id in sorted({s for r in results for s in r.informed} | set(plan.owned)):
        hit = [
            pack_keys(keys[r.informed.pop(scan_id)])
            for keys, r in zip(unit_keys, results, strict=True)
            if scan_id in r.informed
        ]
        own = pack_keys(plan.keys[plan.owned[scan_id]]) if scan_id in plan.owned else none
        tiles = np.union1d(np.concatenate([none, *hit]), own)
        if len(tiles):
            yield scan_id, tiles, np.isin(tiles, own)


def _partition(keys: np.ndarray, n: int) -> np.ndarray:
    """Part of each tile: by tile key, so a tile always goes to the same part."""
    if n == 1:
        return np.zeros(len(keys), np.int64)
    h = (keys[:, 0] * 73856093) ^ (keys[:, 1] * 19349663) ^ (keys[:, 2] * 83492791)
    return np.mod(h, n)


# --------------------------------------------------------------------------------------------
# meshing


@dataclass(frozen=True)
class MeshUnit:
    """Mesh the tiles ``keys`` of a scene: ``data_keys`` are the tiles that exist among them
    and their upper neighbours (the one-voxel halo), ``spheres`` the fused scans that may
    inform them (edge refinement)."""

    group_path: str
    grid: dict[str, Any]
    params: dict[str, Any]
    keys: np.ndarray
    data_keys: np.ndarray
    spheres: list[Sphere]
    refine: bool
    bounds: list[float] | None


class _ReadOnlyTiles:
    """Tiles of a Zarr array as an engine TileStore, for reading those in ``keys``."""

    def __init__(self, tiles: ZarrTiles, keys: np.ndarray) -> None:
        self._tiles = tiles
        self._keys = keys
        self.tile_size = tiles.tile_size

    def keys(self) -> np.ndarray:
        return self._keys

    def read(self, keys: np.ndarray) -> np.ndarray:
        return self._tiles.read(keys)


def mesh_unit(unit: MeshUnit) -> list[bytes]:
    """The mesh of each tile of ``unit.keys``, in order, encoded for the scene's mesh cache
    (:func:`storage.mesh_cache.encode_tile_mesh`)."""
    grid = GridSpec.from_dict(unit.grid)
    params = FusionParams.from_dict(unit.params)
    group = Path(unit.group_path)
    store = _ReadOnlyTiles(ZarrTiles.open(group), unit.data_keys)
    load = _Scans(group, params)

    def scans() -> Iterator[PreparedScan]:
        for scan_id in scans_near(unit.spheres, unit.keys, grid):
            yield load(scan_id)

    tm = mesh_tiles(
        store, grid, params, scans() if unit.refine else (), keys=unit.keys, refine=unit.refine,
        bounds=unit.bounds,
    )  # fmt: skip
    order = np.searchsorted(pack_keys(tm.keys), pack_keys(unit.keys))
    return [encode_tile_mesh(tm, int(n)) for n in order.tolist()]


# --------------------------------------------------------------------------------------------
# runners


class Runner(Protocol):
    """Runs units of work: in this process, or on a cluster (service.cluster)."""

    @property
    def workers(self) -> int:
        """How many units it runs at once (a scene splits its tiles into as many parts)."""
        ...

    def map(
        self,
        fn: Callable[[Item], Result],
        units: Sequence[Item],
        done: Callable[[int], None] | None = None,
    ) -> list[Result]:
        """``fn`` of every unit, in order; ``done(i)`` as unit ``i`` finishes (progress)."""
        ...


class InProcess:
    """The default runner: one unit after the other, here."""

    workers = 1

    def map(
        self,
        fn: Callable[[Item], Result],
        units: Sequence[Item],
        done: Callable[[int], None] | None = None,
    ) -> list[Result]:
        results = []
        for i, unit in enumerate(units):
            results.append(fn(unit))
            if done is not None:
                done(i)
        return results
