"""Units of work: a plan's tiles split among workers, each part integrated on its own
(docs/storage.md, "Units that can run again"; DESIGN.md "Scale-out").

A :class:`TileUnit` is plain, picklable data: where the scene lives, which tiles, which
scans to add to or subtract from each. :func:`integrate_unit` runs one wherever the
store's files are visible: in this process, in a worker process, on a cluster. It reads
the committed chunks and writes the tiles it changes to the scene's staging area, so a unit
killed at any point and run again gives the same bits; the scene's checkpoint publishes
the staged chunks once every unit of the group has finished.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from rangefuse.engine import FusionParams, GridSpec, prepare_scan
from rangefuse.engine.fusion import integrate_seen
from rangefuse.engine.grid import unpack_keys
from rangefuse.engine.planner import View

from .archive import ScanArchive
from .staging import Staging
from .tile_cache import TileCache
from .zarr_tiles import ZarrTiles

__all__ = ["InProcess", "Runner", "TileUnit", "UnitResult", "integrate_unit", "make_units"]


@dataclass(frozen=True)
class TileUnit:
    """Add and subtract scans in some tiles of a scene.

    ``steps`` lists ``(scan_id, rows, free, sign)``: the rows of ``keys`` the archived scan
    has in view, whether it sees each as free space throughout, and 1 to add it or -1 to
    subtract it (exact removal). ``new`` marks tiles that start from unknown instead of their
    committed chunk (created, or rebuilt).
    """

    group_path: str
    staging_path: str
    grid: dict[str, Any]
    params: dict[str, Any]
    keys: np.ndarray
    new: np.ndarray
    steps: list[tuple[str, np.ndarray, np.ndarray, int]]
    cache_mb: float


@dataclass(frozen=True)
class UnitResult:
    informed: dict[str, np.ndarray]  # rows of the unit's keys each scan informs
    voxel_updates: int


def integrate_unit(unit: TileUnit) -> UnitResult:
    """Carry out a unit: stage (and fsync) every tile it changes; returns what it informed.

    Tiles are the outer loop: each tile is read once and staged once, whatever the number
    of scans (they are loaded from the archive first). No other unit of the group has any
    of the unit's tiles.
    """
    grid = GridSpec.from_dict(unit.grid)
    params = FusionParams.from_dict(unit.params)
    group = Path(unit.group_path)
    tiles = ZarrTiles.open(group)
    staging = Staging(Path(unit.staging_path), tiles)
    archive = ScanArchive(group)
    cache = TileCache(tiles, staging, int(unit.cache_mb * 2**20))
    scans = [prepare_scan(archive.get(scan_id), params) for scan_id, _, _, _ in unit.steps]
    n = len(unit.keys)
    # per step and tile: -1 out of view, 0 partial, 1 free throughout
    status = np.full((len(scans), n), -1, np.int8)
    for k, (_, rows, free, _) in enumerate(unit.steps):
        status[k, rows] = free.astype(np.int8)
    hit = np.zeros((len(scans), n), np.bool_)
    updates = 0
    for start in range(0, n, cache.batch):
        part = np.arange(start, min(n, start + cache.batch))
        data = cache.fetch(unit.keys[part], unit.new[part])
        for k, prepared in enumerate(scans):
            seen = np.flatnonzero(status[k, part] >= 0)
            if len(seen) == 0:
                continue
            count = integrate_seen(
                prepared, grid, unit.keys[part], data, seen, status[k, part[seen]] == 1,
                unit.steps[k][3],
            )  # fmt: skip
            hit[k, part] = count > 0
            updates += int(count.sum())
        cache.store(unit.keys[part], data)
    staging.fsync(unpack_keys(cache.flush()))
    informed = {scan_id: np.flatnonzero(hit[k]) for k, (scan_id, *_) in enumerate(unit.steps)}
    return UnitResult(informed=informed, voxel_updates=updates)


def make_units(
    keys: np.ndarray,
    new: np.ndarray,
    views: Sequence[View],
    n_parts: int,
    **where: Any,
) -> list[TileUnit]:
    """Split the tiles ``keys`` (with their ``new`` flags) among ``n_parts`` units by key
    (a tile always goes to the same part: one writer per tile). ``views`` index ``keys``;
    ``where`` gives the units' other fields (paths, grid, params, cache budget per unit)."""
    n_parts = max(1, min(n_parts, len(keys)))
    part_of = _partition(keys, n_parts)
    units = []
    for p in range(n_parts):
        mine = np.flatnonzero(part_of == p)
        local = np.full(len(keys), -1, np.int64)
        local[mine] = np.arange(len(mine))
        steps = []
        for view in views:
            sel = local[view.rows] >= 0
            if sel.any():
                steps.append((view.scan_id, local[view.rows[sel]], view.free[sel], view.sign))
        units.append(TileUnit(keys=keys[mine], new=new[mine], steps=steps, **where))
    return units


def _partition(keys: np.ndarray, n: int) -> np.ndarray:
    """Part of each tile: by tile key, so a tile always goes to the same part."""
    if n == 1:
        return np.zeros(len(keys), np.int64)
    h = (keys[:, 0] * 73856093) ^ (keys[:, 1] * 19349663) ^ (keys[:, 2] * 83492791)
    return np.mod(h, n)


class Runner(Protocol):
    """Runs units of work: in this process, on worker processes, on a cluster."""

    workers: int

    def map(
        self, fn: Callable[[TileUnit], UnitResult], units: list[TileUnit]
    ) -> list[UnitResult]: ...


class InProcess:
    """The default runner: one unit after the other, here."""

    workers = 1

    def map(self, fn: Callable[[TileUnit], UnitResult], units: list[TileUnit]) -> list[UnitResult]:
        return [fn(u) for u in units]
