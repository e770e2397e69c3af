"""A persistent, out-of-core scene: the planner's plans carried out on disk (docs/storage.md).

A scan is acknowledged once its archive entry is fsynced and its catalog row committed
(:meth:`~storage.store.Store.store_scan`). Scans are then fused in groups, each in four
stages:

1. **plan**: the tiles the group writes and which scan goes into which
   (:mod:`engine.planner`, with the one-voxel halo: the tiles whose meshes may change);
2. **stage**: the tiles are split among units of work (:mod:`storage.units`) that read the
   committed chunks and stage the tiles they change, so a unit can simply run again;
3. **checkpoint**: one catalog transaction commits the owners and informing scans, the
   scans' states, the tiles' epochs, and the mark that the group's chunks are to be
   published;
4. **publish**: the staged chunks replace the committed ones (:class:`~storage.staging.Staging`).

A kill before the checkpoint leaves only staged chunks, which the next open discards (the
scans are still ``stored`` and fuse again); a kill after it leaves a publish that the next
open finishes. Either way the result is the bits of a run that was never interrupted.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rangefuse.engine import DenseGrid, FusionParams, GridSpec, Scan, ScanNotFoundError
from rangefuse.engine.grid import KEY_LIMIT, pack_keys, unpack_keys
from rangefuse.engine.meshing import HALO_TILES, Mesh
from rangefuse.engine.planner import Plan, Sphere, View, scans_near, tiles_near
from rangefuse.engine.volume import dense_logodds

from ._heap import release_free_memory
from .archive import ScanArchive
from .catalog import ScanRow
from .groups import GROUP_PAIRS, GROUP_SCANS, scan_groups
from .mesh_cache import MeshCache
from .staging import Staging
from .store import (
    CACHE_MB,
    DEFAULT_SCENE,
    STORE_VERSION,
    Store,
    StoreError,
    check_same,
)
from .tile_cache import cache_tiles
from .tile_store import ZarrTileStore
from .units import (
    InProcess,
    MeshUnit,
    PlanUnit,
    Runner,
    TileUnit,
    UnitResult,
    consumed_views,
    integrate_unit,
    make_units,
    mesh_unit,
    plan_unit,
    tile_scan_rows,
)
from .zarr_tiles import TileArrayError, ZarrTiles

__all__ = ["Scene", "SceneReport", "open_scene", "open_store"]

#: The halo of the plans (engine.planner): the scene keeps tile meshes up to date.
MESH_HALO = 1
#: Fewest tiles a meshing unit takes (each loads the scans near its tiles).
_MIN_MESH_BATCH = 256

Progress = Callable[[int, int], None]


@dataclass
class SceneReport:
    """What a change did (DESIGN.md invariant 7: meshing redoes only the changed tiles)."""

    scans: int = 0
    voxel_updates: int = 0
    tiles_written: int = 0
    tiles_created: int = 0
    tiles_deleted: int = 0
    #: Wall seconds in the fusion kernel, summed over units (the rest of a change's time is
    #: planning, reading, staging, publishing and the catalog).
    fuse_seconds: float = 0.0


def _around(existing: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Mask of the tiles ``existing`` among ``keys`` and their upper neighbours (the tiles a
    mesh of ``keys`` reads)."""
    wanted = np.concatenate([keys + d for d in HALO_TILES])
    return np.isin(pack_keys(existing), pack_keys(wanted))


def _totals(results: Sequence[UnitResult]) -> tuple[int, float]:
    """The voxel updates and the seconds in the fusion kernel, over all units."""
    return sum(r.voxel_updates for r in results), sum(r.fuse_seconds for r in results)


def _reach_box(spheres: Sequence[Sphere], grid: GridSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """The box of tile keys ``[lo, hi]`` that holds every tile within reach of the spheres
    (their radius and the planner's one tile of slack, and a tile more against rounding), or
    None when a sphere is unbounded (or there is none)."""
    if not spheres or not all(math.isfinite(s.radius_m) for s in spheres):
        return None
    tile_m = grid.tile_size_m
    origins = np.array([s.origin for s in spheres], np.float64)
    radii = np.array([s.radius_m for s in spheres], np.float64)[:, None] + tile_m
    lo = np.floor((origins - radii).min(axis=0) / tile_m).astype(np.int64) - 1
    hi = np.floor((origins + radii).max(axis=0) / tile_m).astype(np.int64) + 1
    limit = KEY_LIMIT - 1
    return np.clip(lo, -limit, limit), np.clip(hi, -limit, limit)


def _box_ranges(lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int]]:
    """Ranges of packed keys ``[lo, hi]`` that hold the box of tile keys ``[lo, hi]``: one
    per x (keys pack x, then y, then z)."""
    return [
        (int(pack_keys(np.array([[x, lo[1], lo[2]]]))[0]),
         int(pack_keys(np.array([[x, hi[1], hi[2]]]))[0]))
        for x in range(int(lo[0]), int(hi[0]) + 1)
    ]  # fmt: skip


@dataclass(frozen=True)
class _Work:
    """A plan, the rows of its tiles that units stage, and the units."""

    plan: Plan
    written: np.ndarray
    units: list[TileUnit]
    staging: Staging


class Scene:
    """One scene of a store; open with :func:`open_store` or :func:`open_scene`, close when
    done.

    Opening recovers from an interrupted run (``docs/storage.md``): the report is in
    :attr:`recovered`.
    """

    def __init__(
        self,
        store: Store,
        scene_id: str,
        grid: GridSpec,
        params: FusionParams,
        cache_mb: float,
        runner: Runner | None,
        lock_fd: int,
    ) -> None:
        self.store = store
        self._lock_fd = lock_fd
        self.owns_store = False
        self.path = store.path
        self.scene_id = scene_id
        self.grid = grid
        self.params = params
        self.catalog = store.catalog
        self.group_path = store.scene_path(scene_id) / "scene.zarr"
        self.tiles = ZarrTiles.open(self.group_path)
        self.tile_store = ZarrTileStore(self.tiles, self.catalog, scene_id)
        self.staging_root = store.scene_path(scene_id) / "staging"
        self.archive = ScanArchive(self.group_path)
        self.meshes = MeshCache(self.catalog, scene_id)
        self.cache_mb = cache_mb
        self.runner: Runner = runner if runner is not None else InProcess()
        self.recovered = self._recover()

    def close(self) -> None:
        """Release the scene. What an attempt staged and never committed (it failed: a unit
        that died for good, a full disk, an interruption) is dropped now, while the lock is
        held, rather than at the next open: it may be what filled the disk."""
        with contextlib.suppress(Exception):  # never hide why the caller closes: the next
            if self.catalog.publishing(self.scene_id) is None:  # open recovers anyway
                self._discard_staging()
        os.close(self._lock_fd)
        if self.owns_store:
            self.store.close()

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- scans --------------------------------------------------------------------------------
    def scan_rows(self, states: Sequence[str] | None = None) -> list[ScanRow]:
        """The scene's scans in sequence order (optionally only some states)."""
        return self.catalog.scans(self.scene_id, states)

    def __contains__(self, scan_id: object) -> bool:
        return isinstance(scan_id, str) and self.catalog.scan(self.scene_id, scan_id) is not None

    def store_scan(self, scan_id: str, scan: Scan, name: str | None = None) -> ScanRow:
        """Archive a scan durably and record it as ``stored`` (see
        :meth:`~storage.store.Store.store_scan`); :meth:`integrate_pending` fuses it."""
        return self.store.store_scan(self.scene_id, scan_id, scan, name)

    def _spheres(self, states: Sequence[str] = ("fused",)) -> list[Sphere]:
        """The bounding spheres recorded when the scans were stored."""
        return [Sphere(r.id, r.origin, r.reach_m) for r in self.scan_rows(states)]

    # --- integration --------------------------------------------------------------------------
    def integrate_pending(
        self,
        progress: Progress | None = None,
        group_scans: int = GROUP_SCANS,
        group_pairs: int = GROUP_PAIRS,
    ) -> SceneReport:
        """Fuse every ``stored`` scan, in groups of scans that share tiles
        (:func:`~storage.groups.scan_groups`, at most ``group_scans`` each, whose plan
        holds at most ``group_pairs`` (scan, tile) pairs) with a checkpoint after each.

        The result is bit-identical to fusing all the scene's scans at once, in any order.
        """
        pending = self.scan_rows(("stored",))
        report = SceneReport()
        done = 0
        while done < len(pending):
            group = next(scan_groups(pending[done:], self.archive, group_scans))
            done += len(self._integrate_group(group, report, group_pairs))
            if progress is not None:
                progress(done, len(pending))
        return report

    def _integrate_group(
        self, new_ids: list[str], report: SceneReport, max_pairs: int = GROUP_PAIRS
    ) -> list[str]:
        """Fuse the first scans of ``new_ids`` whose plan holds at most ``max_pairs``
        (scan, tile) pairs (one scan at least); returns their ids."""
        work = self._group_work(new_ids, max_pairs)
        taken = list(work.plan.owned)
        self._commit_group(work, taken, self._run(work.units), report)
        del work
        release_free_memory()  # the group's memory, before the next group's plan
        return taken

    def _commit_group(
        self, work: _Work, new_ids: list[str], results: list[UnitResult], report: SceneReport
    ) -> None:
        """The checkpoint of a group whose units have all finished (and publish)."""
        updates, fuse_seconds = _totals(results)
        plan = work.plan
        unit_keys = [unit.keys for unit in work.units]
        work.units.clear()  # they ran: their steps go before the catalog's rows are made
        self._checkpoint(
            work.staging,
            tile_scan_rows(unit_keys, results, plan),
            fused=new_ids,
            changed=pack_keys(plan.keys[work.written]),
        )
        report.scans += len(new_ids)
        report.voxel_updates += updates
        report.fuse_seconds += fuse_seconds
        report.tiles_created += int(plan.created.sum())
        report.tiles_written += len(work.written)

    def _group_work(self, new_ids: list[str], max_pairs: int | None = None) -> _Work:
        """The plan of fusing the scans ``new_ids`` and its units of work.

        The plan sees the tiles and the earlier scans within reach of the new scans (their
        spheres recorded at upload bound every tile they allocate or have in view), found
        through the catalog's indexes: a group's cost does not grow with the scene."""
        rows = [self.catalog.scan(self.scene_id, scan_id) for scan_id in new_ids]
        reach = [Sphere(r.id, r.origin, r.reach_m) for r in rows if r is not None]
        box = _reach_box(reach, self.grid)
        if box is None:  # a scan of unbounded reach: everything
            existing, spheres = self.catalog.tile_keys(self.scene_id), self._spheres()
        else:
            existing = self._tile_keys_in(*box)
            lo_m = box[0] * self.grid.tile_size_m
            hi_m = (box[1] + 1) * self.grid.tile_size_m
            near = self.catalog.scans_near_box(
                self.scene_id, lo_m.tolist(), hi_m.tolist(), self.grid.tile_size_m
            )  # fmt: skip
            spheres = [Sphere(r.id, r.origin, r.reach_m) for r in near]
        return self._work(self._plan(kind="add", existing=existing, scans=new_ids,
                                     spheres=spheres, max_pairs=max_pairs))  # fmt: skip

    def _tile_keys_in(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Packed keys of the existing tiles in the box of tile keys ``[lo, hi]``, sorted."""
        packed = self.catalog.tile_keys_in_ranges(self.scene_id, _box_ranges(lo, hi))
        keys = unpack_keys(packed)
        inside = np.all((keys >= lo) & (keys <= hi), axis=1)
        return packed[inside]

    def _plan(self, **what: Any) -> tuple[Plan, list[View]]:
        """A plan and its views, made by a planning unit on the runner."""
        unit = PlanUnit(str(self.group_path), self.grid.to_dict(), self.params.to_dict(),
                        halo=MESH_HALO, **what)  # fmt: skip
        ((plan, views),) = self.runner.map(plan_unit, [unit])
        return plan, views

    def _work(self, planned: tuple[Plan, list[View]]) -> _Work:
        """A plan's classified steps, the rows whose chunks are staged (created, or in a
        scan's view), and its units of work: the rows split by key (one writer per tile)."""
        plan, views = planned
        rows = np.unique(np.concatenate([np.flatnonzero(plan.created), *(v.rows for v in views)]))
        position = np.full(len(plan.keys), -1, np.int64)
        position[rows] = np.arange(len(rows))
        n_parts = max(1, min(self.runner.workers, len(rows)))
        # a staging folder of the attempt's own: a unit of an abandoned attempt that still
        # runs somewhere writes where nothing is published
        self._discard_staging()
        staging = Staging(self.staging_root / uuid.uuid4().hex[:16], self.tiles)
        units = make_units(
            plan.keys[rows], plan.created[rows], consumed_views(views, position), n_parts,
            group_path=str(self.group_path), staging_path=str(staging.folder),
            grid=self.grid.to_dict(), params=self.params.to_dict(),
            cache_mb=self.cache_mb / n_parts,
        )  # fmt: skip
        return _Work(plan, rows, units, staging)

    def _run(self, units: list[TileUnit]) -> list[UnitResult]:
        return self.runner.map(integrate_unit, units)

    def _discard_staging(self) -> int:
        """Drop what attempts that never reached their checkpoint staged; returns the
        tiles."""
        staged = 0
        for folder in self._staged_folders():
            with contextlib.suppress(TileArrayError):  # a damaged pack is discarded all the same
                staged += len(Staging(folder, self.tiles).staged_keys())
        shutil.rmtree(self.staging_root, ignore_errors=True)
        return staged

    def _staged_folders(self) -> list[Path]:
        try:
            return sorted(p for p in self.staging_root.iterdir() if p.is_dir())
        except FileNotFoundError:
            return []

    def _checkpoint(
        self,
        staging: Staging,
        rows: Iterable[tuple[str, np.ndarray, np.ndarray]] = (),
        fused: Sequence[str] = (),
        changed: np.ndarray | None = None,
        deleted: np.ndarray | None = None,
        removed: tuple[str, list[tuple[int, int]] | None] | None = None,
    ) -> None:
        """Stage the deletions, hold the room the publish needs (:meth:`Staging.reserve`),
        commit the catalog in one transaction (the units have staged and fsynced their tiles;
        ``rows``: per scan, the packed keys of the tiles it informs or owns and whether it
        owns each; ``removed``: a scan to forget and the packed-key ranges its tiles lie in,
        None for all), then publish the staged chunks."""
        none = np.zeros(0, np.int64)
        deleted = none if deleted is None else deleted
        if len(deleted):
            staging.delete(unpack_keys(deleted))
            staging.finish()
        staging.reserve()  # a disk too full to publish fails the group here, not after
        with self.catalog.transaction():
            self.catalog.add_tile_scans(self.scene_id, rows)
            if removed is not None:
                scan_id, ranges = removed
                self.catalog.remove_tile_scans(self.scene_id, scan_id, ranges)
                self.catalog.delete_scan(self.scene_id, scan_id)
            self.catalog.set_scan_state(self.scene_id, list(fused), "fused")
            self.meshes.bump(np.union1d(none if changed is None else changed, deleted))
            self.catalog.journal_clear(self.scene_id)  # a version-1 journal, now rebuilt
            self.catalog.set_publishing(self.scene_id, staging.folder.name)
        self._publish(staging.folder.name)

    def _publish(self, attempt: str) -> int:
        """Publish what the attempt ``attempt`` staged (its checkpoint is committed)."""
        published = Staging(self.staging_root / attempt, self.tiles).publish()
        self._discard_staging()  # an abandoned attempt's late writes
        with self.catalog.transaction():
            self.catalog.set_publishing(self.scene_id, None)
        return published

    # --- removal ------------------------------------------------------------------------------
    def remove(self, scan_id: str) -> SceneReport:
        """Remove a scan: subtract exactly its contribution, drop the tiles it alone owned,
        then delete it from the archive. Restores, bit for bit, the scene without it."""
        row = self.catalog.scan(self.scene_id, scan_id)
        if row is None:
            raise ScanNotFoundError(f"scan {scan_id!r} is not in the scene")
        if row.state == "stored":  # never fused: nothing to subtract
            with self.catalog.transaction():
                self.catalog.delete_scan(self.scene_id, scan_id)
            self.archive.delete(scan_id)
            return SceneReport(scans=1)
        with self.catalog.transaction():
            self.catalog.set_scan_state(self.scene_id, [scan_id], "removing")
        return self._remove_now(scan_id)

    def _remove_now(self, scan_id: str) -> SceneReport:
        row = self.catalog.scan(self.scene_id, scan_id)
        assert row is not None
        sphere = Sphere(row.id, row.origin, row.reach_m)
        box = _reach_box([sphere], self.grid)
        existing = self.tile_keys() if box is None else unpack_keys(self._tile_keys_in(*box))
        near = existing[tiles_near(sphere, existing, self.grid)]
        owners = dict(zip(pack_keys(near).tolist(), self.tile_store.owners(near), strict=True))
        planned = self._plan(kind="remove", existing=pack_keys(near), spheres=[sphere],
                             owners=owners)  # fmt: skip
        plan = planned[0]
        work = self._work(planned)
        updates, fuse_seconds = _totals(self._run(work.units))
        written = work.written
        self._checkpoint(
            work.staging, changed=pack_keys(plan.keys[written]),
            deleted=pack_keys(plan.deleted),
            removed=(scan_id, None if box is None else _box_ranges(*box)),
        )  # fmt: skip
        self.archive.delete(scan_id)
        return SceneReport(
            scans=1, voxel_updates=updates, tiles_written=len(written),
            tiles_deleted=len(plan.deleted), fuse_seconds=fuse_seconds,
        )  # fmt: skip

    # --- recovery -----------------------------------------------------------------------------
    def _recover(self) -> dict[str, int]:
        """Bring the scene back to its last committed state after an interruption."""
        report = {"published": 0, "discarded": 0, "partials": 0, "rebuilt_tiles": 0}
        attempt = self.catalog.publishing(self.scene_id)
        if attempt is not None:  # committed, publish cut short
            report["published"] = self._publish(attempt)
        else:  # staged by a group that never reached its checkpoint
            report["discarded"] = self._discard_staging()
        legacy = self.catalog.journal(self.scene_id)  # a version-1 store killed mid-group
        if len(legacy):
            report["partials"] = self.tiles.remove_partials()
            report["rebuilt_tiles"] = len(legacy)
            self._rebuild(legacy)
        removing = [r.id for r in self.scan_rows(("removing",))]
        for scan_id in removing:
            self._remove_now(scan_id)
        report["removals_resumed"] = len(removing)
        return report

    def _rebuild(self, tiles: np.ndarray) -> None:
        """Recompute tiles (packed keys) from the archived scans the catalog says inform
        them; tiles without an owner go away."""
        info = self.catalog.tile_scans(self.scene_id, tiles)
        owned = np.array([any(own for _, own in info[t]) for t in tiles.tolist()], np.bool_)
        live = tiles[owned]
        informing: dict[str, list[int]] = {}
        for n, t in enumerate(live.tolist()):
            for scan_id, _ in info[t]:
                informing.setdefault(scan_id, []).append(n)
        planned = self._plan(
            kind="rebuild", existing=live,
            informing={s: np.array(rows, np.int64) for s, rows in informing.items()},
        )  # fmt: skip
        work = self._work(planned)
        self._run(work.units)
        self._checkpoint(work.staging, changed=live, deleted=tiles[~owned])

    # --- reading ------------------------------------------------------------------------------
    def tile_keys(self) -> np.ndarray:
        return unpack_keys(self.catalog.tile_keys(self.scene_id))

    def to_dense(self, bounds: Sequence[float] | None = None) -> DenseGrid:
        """The fused log-odds as a dense grid (see :func:`engine.dense_logodds`)."""
        return dense_logodds(self.tile_store, self.grid, bounds)

    def extract_mesh(
        self,
        *,
        refine: bool = True,
        bounds: Sequence[float] | None = None,
        progress: Progress | None = None,
    ) -> tuple[Mesh, dict[str, int]]:
        """The surface as one mesh, re-meshing (in units of work on the runner) only tiles
        whose data (or halo) changed since they were last meshed with the same options;
        returns the mesh and counts. ``progress(tiles, total)`` as units finish."""
        existing = self.tile_keys()
        spheres = self._spheres()

        def mesh(
            batches: list[np.ndarray], done: Callable[[int], None] | None
        ) -> list[list[bytes]]:
            units = [self._mesh_unit(keys, existing, spheres, refine, bounds) for keys in batches]
            return self.runner.map(mesh_unit, units, done)

        # a batch's tiles and their neighbours in a 24th of the cache, but not so few that
        # loading the scans for each batch costs more than meshing it; four units a worker
        # when there are fewer tiles (every worker busy, progress as units finish)
        most = max(_MIN_MESH_BATCH, cache_tiles(self.cache_mb, self.grid.tile_size) // 24)

        def batch(todo: int) -> int:
            return min(most, max(_MIN_MESH_BATCH, -(-todo // (4 * self.runner.workers))))

        return self.meshes.extract(
            existing, self.grid, mesh, refine=refine, bounds=bounds, batch=batch, progress=progress
        )

    def _mesh_unit(
        self,
        keys: np.ndarray,
        existing: np.ndarray,
        spheres: list[Sphere],
        refine: bool,
        bounds: Sequence[float] | None,
    ) -> MeshUnit:
        """Meshing the tiles ``keys``: the tiles it reads, the scans that may inform them."""
        return MeshUnit(
            str(self.group_path), self.grid.to_dict(), self.params.to_dict(), keys,
            data_keys=existing[_around(existing, keys)],
            spheres=[s for s in spheres if scans_near([s], keys, self.grid)],
            refine=refine, bounds=None if bounds is None else list(bounds),
        )  # fmt: skip

    def info(self) -> dict[str, Any]:
        """Scans by state, tiles, bytes on disk, layout version, parameters."""
        rows = self.scan_rows()
        states: dict[str, int] = {}
        for r in rows:
            states[r.state] = states.get(r.state, 0) + 1
        size = 0
        for root, _, files in os.walk(self.path):
            for name in files:
                with contextlib.suppress(FileNotFoundError):
                    size += os.lstat(os.path.join(root, name)).st_size
        return {
            "store": str(self.path),
            "version": STORE_VERSION,
            "scene": self.scene_id,
            "scans": len(rows),
            "scan_states": states,
            "tiles": self.catalog.n_tiles(self.scene_id),
            "bytes_on_disk": size,
            "grid": self.grid.to_dict(),
            "params": self.params.to_dict(),
        }


def open_scene(
    store: Store,
    scene_id: str,
    cache_mb: float = CACHE_MB,
    runner: Runner | None = None,
    wait: bool = False,
) -> Scene:
    """Take the scene's writer lock (waiting for it with ``wait``), recover the scene and
    return it for fusion and removal; closing it releases the lock."""
    grid, params = store.scene_spec(scene_id)
    lock_fd = store.lock_scene(scene_id, wait=wait)
    try:
        return Scene(store, scene_id, grid, params, cache_mb, runner, lock_fd)
    except BaseException:
        os.close(lock_fd)
        raise


def open_store(
    path: str | os.PathLike[str],
    grid: GridSpec | None = None,
    params: FusionParams | None = None,
    *,
    scene_id: str = DEFAULT_SCENE,
    cache_mb: float = CACHE_MB,
    runner: Runner | None = None,
) -> Scene:
    """Open (and recover) a scene of a store for writing, creating the store and the scene
    when ``grid`` and ``params`` are given and they do not exist yet (the command line).

    The returned scene owns the store: closing it closes both.

    Raises
    ------
    StoreError
        Not a store, another layout version (:class:`StoreVersionError`), the scene written
        by another process (:class:`StoreLockedError`), or ``grid``/``params`` that
        disagree with the existing scene (:class:`SceneConflictError`).
    """
    path = Path(path)
    store = Store.open(path, create=grid is not None)
    try:
        row = store.catalog.scene(scene_id)
        if row is None:
            if grid is None or params is None:
                raise StoreError(f"{path}: holds no scene {scene_id!r}")
            store.create_scene(scene_id, grid, params)
        else:
            check_same(path, "grid", row.grid, grid)
            check_same(path, "fusion parameters", row.params, params)
        scene = open_scene(store, scene_id, cache_mb, runner)
        scene.owns_store = True
        scene.recovered.update(store.cleanup_uploads(scene_id))
        return scene
    except BaseException:
        store.close()
        raise
