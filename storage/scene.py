"""A persistent, out-of-core scene: Zarr tiles, the scan archive, the catalog, crash safety.

The write protocol, recovery and layout are described in ``docs/storage.md``. In short:
a scan is acknowledged once its archive entry is fsynced and its catalog row committed;
tiles are integrated in groups of scans through a :class:`TileCache` with a memory budget;
every tile a group may write is journaled first, and the group ends with a checkpoint
(chunks fsynced, then one catalog transaction). Opening a store after a kill rebuilds the
journaled tiles from the committed state, exactly.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from rangefuse.engine import (
    DenseGrid,
    FusionParams,
    GridSpec,
    PreparedScan,
    Scan,
    ScanNotFoundError,
    prepare_scan,
)
from rangefuse.engine.fusion import integrate_seen
from rangefuse.engine.grid import pack_keys, unique_keys, unpack_keys
from rangefuse.engine.meshing import (
    HALO_TILES,
    Mesh,
    TileMeshes,
    mesh_region,
    mesh_tiles,
    stitch,
    tiles_to_mesh,
)
from rangefuse.engine.tiling import FREE, OUT, bounding_sphere, classify_tiles, tiles_touched
from rangefuse.engine.volume import dense_logodds

from .archive import ScanArchive
from .catalog import Catalog, ScanRow
from .zarr_tiles import ZarrTiles

__all__ = [
    "STORE_VERSION",
    "InProcess",
    "Runner",
    "Scene",
    "SceneConflictError",
    "Store",
    "StoreError",
    "StoreLockedError",
    "StoreVersionError",
    "TileUnit",
    "UnitResult",
    "integrate_unit",
    "open_store",
]

STORE_VERSION = 1
_MARKER = "rangefuse-store.json"
#: What a store holds before its marker is written: a creation killed midway is resumed.
_CREATION_NAMES = frozenset(
    {"catalog.sqlite", "catalog.sqlite-wal", "catalog.sqlite-shm", "catalog.sqlite-journal",
     "lock", "scenes",
     f".{_MARKER}.tmp"}
)  # fmt: skip
#: Default memory budget of the tile cache.
CACHE_MB = 512
#: Scans integrated between two checkpoints.
GROUP_SCANS = 8
#: The scene the command line keeps in a store.
DEFAULT_SCENE = "default"

Progress = Callable[[int, int], None]


class StoreError(RuntimeError):
    """A store that cannot be used as asked (the message says why)."""


class StoreVersionError(StoreError):
    """The store was written by a rangefuse with another layout version."""


class StoreLockedError(StoreError):
    """Another process writes the store."""


class SceneConflictError(StoreError):
    """Parameters that disagree with an existing scene."""


# --------------------------------------------------------------------------------------------
# the store: a directory with a marker, a catalog and scenes


class Store:
    """A store directory: the layout marker, the catalog and one folder per scene.

    Many processes may open a store (the service's API process stores uploads while worker
    processes fuse); tiles of a scene are written only by the holder of the scene's writer
    lock (:meth:`open_scene`).
    """

    def __init__(self, path: Path, catalog: Catalog) -> None:
        self.path = path
        self.catalog = catalog

    @staticmethod
    def open(path: str | os.PathLike[str], create: bool = False) -> Store:
        """Open a store (creating an empty one if ``create``); checks the layout version."""
        path = Path(path)
        marker = path / _MARKER
        if marker.exists():
            try:
                meta = json.loads(marker.read_text())
                version = int(meta["version"])
            except (ValueError, KeyError, TypeError) as exc:
                raise StoreError(f"{path}: damaged {_MARKER} ({exc})") from None
            if meta.get("format") != "rangefuse-store":
                raise StoreError(f"{path}: not a rangefuse store")
            if version != STORE_VERSION:
                raise StoreVersionError(
                    f"{path}: store layout version {version}; this rangefuse reads version "
                    f"{STORE_VERSION}"
                )
        elif not create:
            raise StoreError(f"{path}: not a rangefuse store (no {_MARKER})")
        elif path.exists() and (
            not path.is_dir() or any(p.name not in _CREATION_NAMES for p in path.iterdir())
        ):
            raise StoreError(f"{path}: exists and is not an empty folder or a rangefuse store")
        path.mkdir(parents=True, exist_ok=True)
        catalog = Catalog(path / "catalog.sqlite")
        if not marker.exists():
            tmp = path / f".{_MARKER}.tmp"
            tmp.write_text(json.dumps({"format": "rangefuse-store", "version": STORE_VERSION}))
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, marker)
            _fsync_dir(path)
        return Store(path, catalog)

    def close(self) -> None:
        self.catalog.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- scenes -------------------------------------------------------------------------------
    def scene_path(self, scene_id: str) -> Path:
        return self.path / "scenes" / scene_id

    def create_scene(
        self,
        scene_id: str,
        grid: GridSpec,
        params: FusionParams,
        name: str | None = None,
        tenant: str = "local",
    ) -> None:
        """Record a scene and create its Zarr group and tile array."""
        group = self.scene_path(scene_id) / "scene.zarr"
        ZarrTiles.create(group, grid.tile_size)
        with self.catalog.transaction():
            self.catalog.create_scene(
                scene_id, name or scene_id, tenant, grid.to_dict(), params.to_dict()
            )

    def scene_spec(self, scene_id: str) -> tuple[GridSpec, FusionParams]:
        row = self.catalog.scene(scene_id)
        if row is None:
            raise StoreError(f"{self.path}: holds no scene {scene_id!r}")
        return GridSpec.from_dict(row.grid), FusionParams.from_dict(row.params)

    def delete_scene(self, scene_id: str) -> None:
        """Remove a scene and its files (waits for no writer: takes its lock)."""
        lock_fd = _lock_scene(self.scene_path(scene_id), wait=True)
        try:
            self.catalog.delete_scene(scene_id)
            shutil.rmtree(self.scene_path(scene_id) / "scene.zarr", ignore_errors=True)
        finally:
            os.close(lock_fd)
        shutil.rmtree(self.scene_path(scene_id), ignore_errors=True)

    def store_scan(
        self, scene_id: str, scan_id: str, scan: Scan, name: str | None = None
    ) -> ScanRow:
        """Archive a scan durably, then record it as ``stored``: the acknowledgement.

        Needs no writer lock: archive entries are written once under their own name.
        """
        _, params = self.scene_spec(scene_id)
        if self.catalog.scan(scene_id, scan_id) is not None:
            raise SceneConflictError(f"scan {scan_id!r} is already in the scene")
        origin, radius = bounding_sphere(scan, params)  # NumPy only: no kernel in a request
        archive = ScanArchive(self.scene_path(scene_id) / "scene.zarr")
        checksum = archive.put(scan_id, scan, name)
        try:
            self.catalog.add_scan(scene_id, scan_id, name, origin.tolist(), radius, checksum)
        except BaseException:
            archive.delete(scan_id)
            raise
        row = self.catalog.scan(scene_id, scan_id)
        assert row is not None
        return row

    def cleanup_uploads(self, scene_id: str) -> dict[str, int]:
        """Delete archive entries that were never acknowledged (a kill between the archive
        write and the catalog row). Only while no upload to the scene is in flight: at the
        start of the process that uploads (the command line, the service's API process)."""
        archive = ScanArchive(self.scene_path(scene_id) / "scene.zarr")
        report = {"temporaries": archive.remove_temporaries()}
        known = {r.id for r in self.catalog.scans(scene_id)}
        orphans = [s for s in archive.ids() if s not in known]
        for scan_id in orphans:
            archive.delete(scan_id)
        report["orphan_scans"] = len(orphans)
        return report

    def open_scene(
        self,
        scene_id: str,
        cache_mb: float = CACHE_MB,
        runner: Runner | None = None,
        wait: bool = False,
    ) -> Scene:
        """Take the scene's writer lock (waiting for it with ``wait``), recover the scene and
        return it for fusion and removal."""
        grid, params = self.scene_spec(scene_id)
        lock_fd = _lock_scene(self.scene_path(scene_id), wait=wait)
        try:
            return Scene(self, scene_id, grid, params, cache_mb, runner, lock_fd)
        except BaseException:
            os.close(lock_fd)
            raise


def _lock_scene(folder: Path, wait: bool) -> int:
    folder.mkdir(parents=True, exist_ok=True)
    lock_fd = os.open(folder / "lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(lock_fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        holder = os.pread(lock_fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(lock_fd)
        raise StoreLockedError(
            f"{folder}: the scene is being written by another rangefuse process "
            f"(pid {holder}); one writer at a time"
        ) from None
    os.ftruncate(lock_fd, 0)
    os.pwrite(lock_fd, f"{os.getpid()}\n".encode(), 0)
    return lock_fd


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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
            _check_same(path, "grid", row.grid, grid)
            _check_same(path, "fusion parameters", row.params, params)
        scene = store.open_scene(scene_id, cache_mb, runner)
        scene.owns_store = True
        scene.recovered.update(store.cleanup_uploads(scene_id))
        return scene
    except BaseException:
        store.close()
        raise


def _check_same(path: Path, what: str, stored: dict[str, Any], given: Any) -> None:
    if given is None:
        return
    wanted = given.to_dict()
    stored = type(given).from_dict(stored).to_dict()  # a store may use legacy names
    diff = [k for k in sorted(set(stored) | set(wanted)) if stored.get(k) != wanted.get(k)]
    if diff:
        details = ", ".join(
            f"{k}: store has {stored.get(k)!r}, given {wanted.get(k)!r}" for k in diff
        )
        raise SceneConflictError(
            f"{path}: the scene was created with other {what} ({details}); use the store's "
            "parameters or a new store"
        )


# --------------------------------------------------------------------------------------------
# the tile cache


#: Tiles written per call when the cache writes back (bounds the temporary stack).
_WRITE_CHUNK = 256


class TileCache:
    """Tiles in memory under a byte budget; dirty tiles are written back when evicted.

    The budget covers the resident tiles and the batch being worked on: the cache keeps
    at most 3/4 of it in tiles, a batch is 1/4, and :meth:`store` keeps views of the
    caller's batch array instead of copies. Evicted dirty tiles must already be journaled
    (the scene journals a group's tiles before integrating it).
    """

    def __init__(self, tiles: ZarrTiles, tile_size: int, budget_bytes: int) -> None:
        self.tiles = tiles
        self.T = tile_size
        self.tile_bytes = tile_size**3 * 8
        self.capacity = _cache_tiles(budget_bytes / 2**20, tile_size)
        self._data: OrderedDict[int, np.ndarray] = OrderedDict()
        self._dirty: set[int] = set()
        self.written: set[int] = set()  # packed keys written since the last checkpoint
        self.reads = 0
        self.writes = 0

    @property
    def batch(self) -> int:
        """Tiles one integration batch may hold (a third of the resident capacity)."""
        return max(4, self.capacity // 3)

    def fetch(self, keys: np.ndarray, new: np.ndarray) -> np.ndarray:
        """Copies of the tiles ``keys`` (int64 (n, 3)); ``new`` ones start as unknown."""
        packed = pack_keys(keys)
        out = np.zeros((len(keys), self.T, self.T, self.T), np.int64)
        missing = []
        for n, p in enumerate(packed.tolist()):
            tile = self._data.get(p)
            if tile is not None:
                self._data.move_to_end(p)
                out[n] = tile
            elif not new[n] or p in self.written:  # a new tile may have been evicted
                missing.append(n)
        if missing:
            rows = np.array(missing, np.int64)
            out[rows] = self.tiles.read(keys[rows])
            self.reads += len(rows)
        return out

    def store(self, keys: np.ndarray, data: np.ndarray) -> None:
        """Put updated tiles back (dirty); evicts the least recently used beyond capacity."""
        for p, tile in zip(pack_keys(keys).tolist(), data, strict=True):
            self._data[p] = tile  # a view: the batch array lives while a tile of it is cached
            self._data.move_to_end(p)
            self._dirty.add(p)
        self._evict()

    def drop(self, keys: np.ndarray) -> None:
        for p in pack_keys(keys).tolist():
            self._data.pop(p, None)
            self._dirty.discard(p)

    def _evict(self) -> None:
        if len(self._data) <= self.capacity:
            return
        victims = []
        while len(self._data) > self.capacity * 3 // 4:
            p, tile = self._data.popitem(last=False)
            if p in self._dirty:
                victims.append((p, tile))
                self._dirty.discard(p)
        self._write(victims)

    def _write(self, items: list[tuple[int, np.ndarray]]) -> None:
        for start in range(0, len(items), _WRITE_CHUNK):  # bounded temporary copies
            part = items[start : start + _WRITE_CHUNK]
            packed = np.array([p for p, _ in part], np.int64)
            self.tiles.write(unpack_keys(packed), np.stack([t for _, t in part]))
            self.written.update(packed.tolist())
            self.writes += len(part)

    def flush(self) -> np.ndarray:
        """Write every dirty tile; returns the packed keys written since the last call."""
        self._write([(p, self._data[p]) for p in sorted(self._dirty)])
        self._dirty.clear()
        written = np.array(sorted(self.written), np.int64)
        self.written = set()
        return written

    def clear(self) -> None:
        self._data.clear()
        self._dirty.clear()


# --------------------------------------------------------------------------------------------
# units of work and runners


@dataclass(frozen=True)
class TileUnit:
    """Integrate scans into some tiles of a scene: plain data, picklable (DESIGN.md
    "Scale-out": the same unit runs in-process, in a worker process or on a Dask worker).

    ``scans`` lists ``(scan_id, rows, free)``: the rows of ``keys`` the archived scan
    updates and whether it sees each as free space throughout; ``new`` marks tiles that
    start from unknown instead of their stored chunk (created, or rebuilt after a crash);
    ``sign`` is 1 to add the scans, -1 to subtract them (exact removal).
    """

    group_path: str
    grid: dict[str, Any]
    params: dict[str, Any]
    keys: np.ndarray
    new: np.ndarray
    scans: list[tuple[str, np.ndarray, np.ndarray]]
    cache_mb: float
    sign: int = 1


@dataclass(frozen=True)
class UnitResult:
    informed: dict[str, np.ndarray]  # rows of the unit's keys each scan informs
    voxel_updates: int


def integrate_unit(unit: TileUnit) -> UnitResult:
    """Add (or subtract) the unit's scans to its tiles and write them back (fsynced).

    Tiles are the outer loop: each tile is read once and written once, whatever the number
    of scans (they are loaded from the archive first: a group of scans, a few MB). The
    caller holds the store's writer lock and has journaled the tiles; no other unit has any
    of them.
    """
    grid = GridSpec.from_dict(unit.grid)
    params = FusionParams.from_dict(unit.params)
    group = Path(unit.group_path)
    tiles = ZarrTiles.open(group)
    archive = ScanArchive(group)
    cache = TileCache(tiles, grid.tile_size, int(unit.cache_mb * 2**20))
    scans = [prepare_scan(archive.get(scan_id), params) for scan_id, _, _ in unit.scans]
    n = len(unit.keys)
    # per scan and tile: -1 out of view, 0 partial, 1 free throughout
    status = np.full((len(scans), n), -1, np.int8)
    for k, (_, rows, free) in enumerate(unit.scans):
        status[k, rows] = free.astype(np.int8)
    hit = np.zeros((len(scans), n), np.bool_)
    updates = 0
    for start in range(0, n, cache.batch):
        part = np.arange(start, min(n, start + cache.batch))
        data = cache.fetch(unit.keys[part], unit.new[part])
        data[unit.new[part]] = 0  # a rebuilt tile starts from unknown, whatever is on disk
        for k, prepared in enumerate(scans):
            seen = np.flatnonzero(status[k, part] >= 0)
            if len(seen) == 0:
                continue
            count = integrate_seen(
                prepared, grid, unit.keys[part], data, seen, status[k, part[seen]] == 1, unit.sign
            )
            hit[k, part] = count > 0
            updates += int(count.sum())
        cache.store(unit.keys[part], data)
    written = cache.flush()
    if len(written):
        tiles.fsync(unpack_keys(written))
    informed = {scan_id: np.flatnonzero(hit[k]) for k, (scan_id, _, _) in enumerate(unit.scans)}
    return UnitResult(informed=informed, voxel_updates=updates)


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


def _partition(keys: np.ndarray, n: int) -> np.ndarray:
    """Worker of each tile: by tile key, so a tile always goes to the same worker."""
    if n == 1:
        return np.zeros(len(keys), np.int64)
    h = (keys[:, 0] * 73856093) ^ (keys[:, 1] * 19349663) ^ (keys[:, 2] * 83492791)
    return np.mod(h, n)


# --------------------------------------------------------------------------------------------
# the scene


@dataclass
class SceneReport:
    """What a change did (DESIGN.md invariant 7: meshing redoes only the changed tiles)."""

    scans: int = 0
    voxel_updates: int = 0
    tiles_written: int = 0
    tiles_created: int = 0
    tiles_deleted: int = 0


def _cache_tiles(cache_mb: float, tile_size: int) -> int:
    """Tiles a cache of ``cache_mb`` holds (see :class:`TileCache`)."""
    return max(8, int(cache_mb * 2**20) // (tile_size**3 * 8) * 3 // 4)


def _with_lower_neighbours(packed: np.ndarray) -> np.ndarray:
    """The tiles and the 7 tiles whose one-voxel halo they are (meshing reads upwards)."""
    keys = unpack_keys(packed)
    return np.unique(pack_keys(np.concatenate([keys - off for off in HALO_TILES])))


class _TileReader:
    """The scene's tiles as an engine :class:`~engine.volume.TileStore` (read side)."""

    def __init__(self, scene: Scene) -> None:
        self._scene = scene
        self.tile_size = scene.grid.tile_size

    def keys(self) -> np.ndarray:
        return unpack_keys(self._scene.catalog.tile_keys(self._scene.scene_id))

    def read(self, keys: np.ndarray) -> np.ndarray:
        return self._scene.tiles.read(np.asarray(keys, np.int64).reshape(-1, 3))

    def owners(self, keys: np.ndarray) -> list[frozenset[str]]:
        info = self._scene.catalog.tile_scans(self._scene.scene_id, pack_keys(keys))
        return [frozenset(s for s, own in info[p] if own) for p in pack_keys(keys).tolist()]

    def write(
        self,
        keys: np.ndarray,
        data: np.ndarray,
        owners: Sequence[frozenset[str]],
        *,
        take: bool = False,
    ) -> None:
        raise StoreError("tiles of a stored scene change through Scene methods only")

    def delete(self, keys: np.ndarray) -> None:
        raise StoreError("tiles of a stored scene change through Scene methods only")


def _encode_tile_mesh(tm: TileMeshes, n: int) -> bytes:
    v0, v1 = int(tm.vertex_offsets[n]), int(tm.vertex_offsets[n + 1])
    f0, f1 = int(tm.face_offsets[n]), int(tm.face_offsets[n + 1])
    head = np.array([v1 - v0, f1 - f0], np.int64)
    return b"".join(
        [
            head.tobytes(),
            np.ascontiguousarray(tm.vertex_keys[v0:v1], np.int64).tobytes(),
            np.ascontiguousarray(tm.vertices[v0:v1], np.float64).tobytes(),
            np.ascontiguousarray(tm.faces[f0:f1] - v0, np.int64).tobytes(),
            np.ascontiguousarray(tm.inferred[f0:f1], np.bool_).tobytes(),
        ]
    )


def _decode_tile_meshes(key: np.ndarray, blobs: Sequence[bytes]) -> TileMeshes:
    vk, vs, fs, inf, v_off, f_off = [], [], [], [], [0], [0]
    for blob in blobs:
        nv, nf = np.frombuffer(blob, np.int64, 2)
        at = 16
        vk.append(np.frombuffer(blob, np.int64, nv * 4, at).reshape(-1, 4))
        at += nv * 32
        vs.append(np.frombuffer(blob, np.float64, nv * 3, at).reshape(-1, 3))
        at += nv * 24
        fs.append(np.frombuffer(blob, np.int64, nf * 3, at).reshape(-1, 3) + v_off[-1])
        at += nf * 24
        inf.append(np.frombuffer(blob, np.bool_, nf, at))
        v_off.append(v_off[-1] + int(nv))
        f_off.append(f_off[-1] + int(nf))
    return TileMeshes(
        keys=key,
        vertex_offsets=np.array(v_off, np.int64),
        face_offsets=np.array(f_off, np.int64),
        vertex_keys=np.concatenate([np.zeros((0, 4), np.int64), *vk]),
        vertices=np.concatenate([np.zeros((0, 3)), *vs]),
        faces=np.concatenate([np.zeros((0, 3), np.int64), *fs]),
        inferred=np.concatenate([np.zeros(0, np.bool_), *inf]),
    )


class Scene:
    """One scene of a store; open with :func:`open_store`, close when done.

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
        self.archive = ScanArchive(self.group_path)
        self.cache_mb = cache_mb
        self.runner: Runner = runner if runner is not None else InProcess()
        self._prepared: OrderedDict[str, PreparedScan] = OrderedDict()
        self.recovered = self._recover()

    def close(self) -> None:
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
        """Archive a scan durably and record it as ``stored`` (see :meth:`Store.store_scan`);
        :meth:`integrate_pending` fuses it."""
        return self.store.store_scan(self.scene_id, scan_id, scan, name)

    def _load(self, scan_id: str) -> PreparedScan:
        prepared = self._prepared.get(scan_id)
        if prepared is None:
            prepared = prepare_scan(self.archive.get(scan_id), self.params)
            self._prepared[scan_id] = prepared
            while len(self._prepared) > 2:  # memory is one scan or two, not the scene
                self._prepared.popitem(last=False)
        else:
            self._prepared.move_to_end(scan_id)
        return prepared

    def _scans_near(self, keys: np.ndarray, exclude: set[str] | None = None) -> list[ScanRow]:
        """Fused scans whose bounding sphere meets the box of the tiles ``keys``."""
        if len(keys) == 0:
            return []
        tile_m = self.grid.tile_size_m
        lo = keys.min(axis=0) * tile_m
        hi = (keys.max(axis=0) + 1) * tile_m
        out = []
        for row in self.scan_rows(("fused",)):
            if exclude and row.id in exclude:
                continue
            o = np.asarray(row.origin)
            d = float(np.sqrt(np.sum(np.maximum(np.maximum(lo - o, o - hi), 0.0) ** 2)))
            if not math.isfinite(row.reach_m) or d <= row.reach_m + tile_m:
                out.append(row)
        return out

    # --- integration --------------------------------------------------------------------------
    def integrate_pending(
        self, progress: Progress | None = None, group_scans: int = GROUP_SCANS
    ) -> SceneReport:
        """Fuse every ``stored`` scan, in groups of scans with a checkpoint after each.

        The result is bit-identical to fusing all the scene's scans at once, in any order.
        """
        pending = [r.id for r in self.scan_rows(("stored",))]
        report = SceneReport()
        for start in range(0, len(pending), group_scans):
            group = pending[start : start + group_scans]
            self._integrate_group(group, report)
            if progress is not None:
                progress(start + len(group), len(pending))
        return report

    def _integrate_group(self, new_ids: list[str], report: SceneReport) -> None:
        grid = self.grid
        existing = unpack_keys(self.catalog.tile_keys(self.scene_id))
        touched = {s: tiles_touched(self._load(s), grid) for s in new_ids}
        all_touched = unique_keys(np.concatenate([np.zeros((0, 3), np.int64), *touched.values()]))
        created = all_touched[~np.isin(pack_keys(all_touched), pack_keys(existing))]
        keys = unique_keys(np.concatenate([existing, created]))
        packed = pack_keys(keys)
        is_new = np.isin(packed, pack_keys(created))
        # which rows each scan updates: the new scans every tile in view (halo 1: the tiles
        # whose meshes they may change), earlier scans the created tiles in view
        plans: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        everything = np.arange(len(keys))
        for scan_id in new_ids:
            plans[scan_id] = self._plan(scan_id, keys, everything)
        if len(created):
            for row in self._scans_near(created, exclude=set(new_ids)):
                rows, free = self._plan(row.id, keys, np.flatnonzero(is_new))
                if len(rows):
                    plans[row.id] = (rows, free)
        written = np.unique(
            np.concatenate([np.flatnonzero(is_new), *[rows for rows, _ in plans.values()]])
        )
        with self.catalog.transaction():
            self.catalog.journal_add(self.scene_id, packed[written])
        informed, updates = self._run_units(keys[written], is_new[written], plans, written)
        report.voxel_updates += updates
        self._checkpoint(
            informed=informed,
            owned={s: pack_keys(t) for s, t in touched.items()},
            fused=new_ids,
            changed=packed[written],
        )
        report.scans += len(new_ids)
        report.tiles_created += len(created)
        report.tiles_written += len(written)

    def _plan(
        self, scan_id: str, keys: np.ndarray, candidates: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        status = classify_tiles(self._load(scan_id), self.grid, keys[candidates], halo=1)
        seen = status != OUT
        return candidates[seen], status[seen] == FREE

    def _run_units(
        self,
        keys: np.ndarray,
        new: np.ndarray,
        plans: dict[str, tuple[np.ndarray, np.ndarray]],
        rows_of_keys: np.ndarray | None = None,
        sign: int = 1,
    ) -> tuple[dict[str, np.ndarray], int]:
        """Split tiles among the runner's workers (by key: one writer per tile) and run a
        :class:`TileUnit` each. ``plans[scan] = (rows, free)`` index ``keys`` (or, with
        ``rows_of_keys``, the array those rows are taken from). Returns the packed keys
        each scan informs and the number of voxel updates."""
        if rows_of_keys is not None:  # plans index a larger array: map to positions in keys
            position = np.full(int(rows_of_keys.max()) + 1 if len(rows_of_keys) else 0, -1)
            position[rows_of_keys] = np.arange(len(rows_of_keys))
            plans = {
                s: (position[rows][position[rows] >= 0], free[position[rows] >= 0])
                for s, (rows, free) in plans.items()
            }
        n_parts = max(1, min(self.runner.workers, len(keys)))
        part_of = _partition(keys, n_parts)
        units = []
        for p in range(n_parts):
            mine = np.flatnonzero(part_of == p)
            local = np.full(len(keys), -1, np.int64)
            local[mine] = np.arange(len(mine))
            scans = []
            for scan_id, (rows, free) in plans.items():
                sel = local[rows] >= 0
                if sel.any():
                    scans.append((scan_id, local[rows[sel]], free[sel]))
            units.append(
                TileUnit(
                    group_path=str(self.group_path),
                    grid=self.grid.to_dict(),
                    params=self.params.to_dict(),
                    keys=keys[mine],
                    new=new[mine],
                    scans=scans,
                    cache_mb=self.cache_mb / n_parts,
                    sign=sign,
                )
            )
        informed: dict[str, list[np.ndarray]] = {}
        updates = 0
        for unit, result in zip(units, self.runner.map(integrate_unit, units), strict=True):
            for scan_id, local_rows in result.informed.items():
                informed.setdefault(scan_id, []).append(pack_keys(unit.keys[local_rows]))
            updates += result.voxel_updates
        return {s: np.concatenate(v) for s, v in informed.items()}, updates

    def _checkpoint(
        self,
        informed: dict[str, np.ndarray],
        owned: dict[str, np.ndarray],
        fused: Sequence[str] = (),
        changed: np.ndarray | None = None,
        deleted: np.ndarray | None = None,
        removed: str | None = None,
    ) -> None:
        """Delete (durably) the tiles that went away, then commit the catalog in one
        transaction. The units have written and fsynced their tiles already."""
        none = np.zeros(0, np.int64)
        if deleted is not None and len(deleted):
            self.tiles.delete(unpack_keys(deleted))
            self.tiles.fsync(unpack_keys(deleted))
        with self.catalog.transaction():
            for scan_id in sorted(set(informed) | set(owned)):
                hit = informed.get(scan_id, np.zeros(0, np.int64))
                own = owned.get(scan_id, np.zeros(0, np.int64))
                tiles = np.union1d(hit, own)
                if len(tiles):
                    self.catalog.add_tile_scans(self.scene_id, scan_id, tiles, np.isin(tiles, own))
            if removed is not None:
                self.catalog.remove_tile_scans(self.scene_id, removed)
                self.catalog.delete_scan(self.scene_id, removed)
            self.catalog.set_scan_state(self.scene_id, list(fused), "fused")
            bump = np.union1d(
                changed if changed is not None else none, deleted if deleted is not None else none
            )
            if len(bump):
                self.catalog.bump_epochs(self.scene_id, _with_lower_neighbours(bump))
            self.catalog.journal_clear(self.scene_id)

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
        tiles, _ = self.catalog.tiles_of_scan(self.scene_id, scan_id)
        info = self.catalog.tile_scans(self.scene_id, tiles)
        alone = np.array(
            [{s for s, own in info[t] if own} <= {scan_id} for t in tiles.tolist()], np.bool_
        )
        with self.catalog.transaction():
            self.catalog.journal_add(self.scene_id, tiles)
        keep = tiles[~alone]
        keys = unpack_keys(keep)
        plan = self._plan(scan_id, keys, np.arange(len(keys)))
        _, updates = self._run_units(keys, np.zeros(len(keys), np.bool_), {scan_id: plan}, sign=-1)
        self._checkpoint(informed={}, owned={}, changed=keep, deleted=tiles[alone], removed=scan_id)
        self.archive.delete(scan_id)
        return SceneReport(
            scans=1, voxel_updates=updates, tiles_written=len(keep), tiles_deleted=int(alone.sum())
        )

    # --- recovery -----------------------------------------------------------------------------
    def _recover(self) -> dict[str, int]:
        """Bring the store back to its last committed state after an interruption."""
        report: dict[str, int] = {}
        journal = self.catalog.journal(self.scene_id)
        report["partials"] = self.tiles.remove_partials() if len(journal) else 0
        report["rebuilt_tiles"] = len(journal)
        if len(journal):
            self._rebuild(journal)
        removing = [r.id for r in self.scan_rows(("removing",))]
        for scan_id in removing:
            self._remove_now(scan_id)
        report["removals_resumed"] = len(removing)
        return report

    def _rebuild(self, tiles: np.ndarray) -> None:
        """Recompute tiles from the archived scans the catalog says inform them."""
        info = self.catalog.tile_scans(self.scene_id, tiles)
        owned = np.array([any(own for _, own in info[t]) for t in tiles.tolist()], np.bool_)
        gone = tiles[~owned]
        live = tiles[owned]
        keys = unpack_keys(live)
        by_scan: dict[str, list[int]] = {}
        for n, t in enumerate(live.tolist()):
            for scan_id, _ in info[t]:
                by_scan.setdefault(scan_id, []).append(n)
        plans = {
            scan_id: self._plan(scan_id, keys, np.array(rows, np.int64))
            for scan_id, rows in sorted(by_scan.items())
        }
        self._run_units(keys, np.ones(len(keys), np.bool_), plans)
        if len(gone):
            self.tiles.delete(unpack_keys(gone))
        if len(tiles):
            self.tiles.fsync(unpack_keys(tiles))
        with self.catalog.transaction():
            self.catalog.bump_epochs(self.scene_id, _with_lower_neighbours(tiles))
            self.catalog.journal_clear(self.scene_id)

    # --- reading ------------------------------------------------------------------------------
    def tile_keys(self) -> np.ndarray:
        return unpack_keys(self.catalog.tile_keys(self.scene_id))

    def to_dense(self, bounds: Sequence[float] | None = None) -> DenseGrid:
        """The fused log-odds as a dense grid (see :func:`engine.dense_logodds`)."""
        return dense_logodds(_TileReader(self), self.grid, bounds)

    def _scan_stream(self, keys: np.ndarray) -> Iterator[PreparedScan]:
        for row in self._scans_near(keys):
            yield self._load(row.id)

    def extract_mesh(
        self, *, refine: bool = True, bounds: Sequence[float] | None = None
    ) -> tuple[Mesh, dict[str, int]]:
        """The surface as one mesh, re-meshing only tiles whose data (or halo) changed since
        they were last meshed with the same options; returns the mesh and counts."""
        lo, hi = mesh_region(self.grid, bounds)
        reader = _TileReader(self)
        keys = tiles_to_mesh(reader.keys(), self.grid, lo, hi)
        packed = pack_keys(keys)
        options = json.dumps(
            {"refine": bool(refine), "bounds": None if bounds is None else list(bounds)}
        )
        epochs = self.catalog.epochs(self.scene_id, packed)
        cached = self.catalog.mesh_cache_get(self.scene_id, packed, options)
        hit = np.array(
            [
                p in cached and cached[p][0] == e
                for p, e in zip(packed.tolist(), epochs.tolist(), strict=True)
            ],
            np.bool_,
        )
        parts = []
        if hit.any():
            parts.append(
                _decode_tile_meshes(keys[hit], [cached[p][1] for p in packed[hit].tolist()])
            )
        todo = np.flatnonzero(~hit)
        batch = max(1, _cache_tiles(self.cache_mb, self.grid.tile_size) // 24)
        for start in range(0, len(todo), batch):
            rows = todo[start : start + batch]
            tm = mesh_tiles(
                reader,
                self.grid,
                self.params,
                self._scan_stream(keys[rows]) if refine else (),
                keys=keys[rows],
                refine=refine,
                bounds=bounds,
            )
            order = np.searchsorted(pack_keys(tm.keys), packed[rows])
            entries = [
                (int(packed[r]), int(epochs[r]), _encode_tile_mesh(tm, int(n)))
                for r, n in zip(rows.tolist(), order.tolist(), strict=True)
            ]
            self.catalog.mesh_cache_put(self.scene_id, options, entries)
            parts.append(tm)
        counts = {"tiles": len(keys), "reused": int(hit.sum()), "meshed": len(todo)}
        return stitch(parts), counts

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
