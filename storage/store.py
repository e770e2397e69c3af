"""A store directory: the layout marker, the catalog, one folder per scene, the writer locks.

Layout and protocol: ``docs/storage.md``. Many processes may open a store (the service's
API process archives uploads while workers fuse); the tiles of a scene are written only by
the holder of the scene's writer lock (:meth:`Store.open_scene`, :func:`open_store`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangefuse.engine import FusionParams, GridSpec, Scan
from rangefuse.engine.classify import bounding_sphere

from ._files import fsync_path
from .archive import ScanArchive, StagedScan
from .catalog import Catalog, ScanRow
from .zarr_tiles import ZarrTiles

__all__ = [
    "CACHE_MB",
    "DEFAULT_SCENE",
    "STORE_VERSION",
    "PendingScan",
    "SceneConflictError",
    "Store",
    "StoreError",
    "StoreLockedError",
    "StoreVersionError",
    "check_same",
]

#: The layout this rangefuse writes. Version 1 (tiles written in place, a journal of tiles in
#: flight rebuilt at open) is read and upgraded on open: its marker is rewritten, and a
#: scene's journal is rebuilt the first time the scene is opened (docs/storage.md).
STORE_VERSION = 4
_READS_VERSIONS = (1, 2, 3, 4)
_MARKER = "rangefuse-store.json"
#: What a store holds before its marker is written: a creation killed midway is resumed.
_CREATION_NAMES = frozenset(
    {"catalog.sqlite", "catalog.sqlite-wal", "catalog.sqlite-shm", "catalog.sqlite-journal",
     "lock", "scenes",
     f".{_MARKER}.tmp"}
)  # fmt: skip
#: Default memory budget of the tile cache.
CACHE_MB = 512
#: The scene the command line keeps in a store.
DEFAULT_SCENE = "default"


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


@dataclass(frozen=True)
class PendingScan:
    """A scan staged in its scene's archive, waiting to be committed
    (:meth:`Store.stage_scan`, :meth:`Store.commit_scans`)."""

    scene_id: str
    scan_id: str
    name: str | None
    #: The scan's bounding sphere (the catalog's ``origin`` and ``radius``).
    origin: list[float]
    radius: float
    far_ranges: int
    sensor: dict[str, Any]
    entry: StagedScan


class Store:
    """A store directory: the layout marker, the catalog and one folder per scene.

    Many processes may open a store (the service's API process stores uploads while worker
    processes fuse); tiles of a scene are written only by the holder of the scene's writer
    lock (:meth:`open_scene`).
    """

    def __init__(self, path: Path, catalog: Catalog) -> None:
        self.path = path
        self.catalog = catalog
        #: Threads that stage a batch of scans side by side (:meth:`store_scans`).
        self._stage_pool: ThreadPoolExecutor | None = None

    @staticmethod
    def open(path: str | os.PathLike[str], create: bool = False) -> Store:
        """Open a store (creating an empty one if ``create``); checks the layout version."""
        path = Path(path)
        marker = path / _MARKER
        version = STORE_VERSION
        if marker.exists():
            try:
                meta = json.loads(marker.read_text())
                version = int(meta["version"])
            except (ValueError, KeyError, TypeError) as exc:
                raise StoreError(f"{path}: damaged {_MARKER} ({exc})") from None
            if meta.get("format") != "rangefuse-store":
                raise StoreError(f"{path}: not a rangefuse store")
            if version not in _READS_VERSIONS:
                raise StoreVersionError(
                    f"{path}: store layout version {version}; this rangefuse reads versions "
                    f"{', '.join(map(str, _READS_VERSIONS))}"
                )
        elif not create:
            raise StoreError(f"{path}: not a rangefuse store (no {_MARKER})")
        elif path.exists() and (
            not path.is_dir() or any(p.name not in _CREATION_NAMES for p in path.iterdir())
        ):
            raise StoreError(f"{path}: exists and is not an empty folder or a rangefuse store")
        path.mkdir(parents=True, exist_ok=True)
        catalog = Catalog(path / "catalog.sqlite")
        if not marker.exists() or version != STORE_VERSION:  # new, or an older one upgraded
            _write_marker(path)
        return Store(path, catalog)

    def close(self) -> None:
        if self._stage_pool is not None:
            self._stage_pool.shutdown()
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
        sensor: dict[str, Any] | None = None,
    ) -> None:
        """Record a scene and create its Zarr group and tile array. ``sensor``: its default
        sensor (``Sensor.to_dict``); without one, its first stored scan's becomes it."""
        group = self.scene_path(scene_id) / "scene.zarr"
        ZarrTiles.create(group, grid.tile_size)
        with self.catalog.transaction():
            self.catalog.create_scene(
                scene_id, name or scene_id, tenant, grid.to_dict(), params.to_dict(), sensor
            )

    def scene_spec(self, scene_id: str) -> tuple[GridSpec, FusionParams]:
        row = self.catalog.scene(scene_id)
        if row is None:
            raise StoreError(f"{self.path}: holds no scene {scene_id!r}")
        return GridSpec.from_dict(row.grid), FusionParams.from_dict(row.params)

    def delete_scene(self, scene_id: str, wait: bool = True) -> None:
        """Remove a scene and its files: takes its writer lock, waiting for it with ``wait``
        (otherwise :class:`StoreLockedError` while a writer holds it)."""
        lock_fd = _lock_scene(self.scene_path(scene_id), wait=wait)
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
        (result,) = self.store_scans([(scene_id, scan_id, scan, name)])
        if isinstance(result, BaseException):
            raise result
        return result

    def store_scans(self, items: Sequence[NewScan]) -> list[ScanRow | Exception]:
        """Store scans that arrived together, ``(scene_id, scan_id, scan, name)`` each, with
        one round of fsyncs and one catalog transaction (a group commit): each is staged
        (:meth:`stage_scan`, side by side in threads), then all are committed at once
        (:meth:`commit_scans`). Returns, in order, each scan's row or the error that refused
        it (a bad scan fails alone); an error of the shared steps (a full disk) fails every
        scan of the batch, and nothing of it stays."""
        checked: list[tuple[list[float], float] | Exception] = []
        for scene_id, scan_id, scan, _ in items:  # the catalog, in this thread (its connection)
            try:
                checked.append(self._check_new(scene_id, scan_id, scan))
            except Exception as exc:
                checked.append(exc)
        if self._stage_pool is None:  # started once: threads cost more than a batch's work
            self._stage_pool = ThreadPoolExecutor(4, thread_name_prefix="rangefuse-stage")

        def stage(i: int) -> PendingScan | Exception:
            sphere = checked[i]
            if isinstance(sphere, Exception):
                return sphere
            try:
                return self._stage(*items[i], *sphere)
            except Exception as exc:
                return exc

        staged = list(self._stage_pool.map(stage, range(len(items))))
        ready = [one for one in staged if isinstance(one, PendingScan)]
        committed = iter(self.commit_scans(ready))
        return [one if isinstance(one, Exception) else next(committed) for one in staged]

    def _check_new(self, scene_id: str, scan_id: str, scan: Scan) -> tuple[list[float], float]:
        """The bounding sphere of a scan new to the scene (errors for an unknown scene or a
        scan id it holds)."""
        _, params = self.scene_spec(scene_id)
        if self.catalog.scan(scene_id, scan_id) is not None:
            raise SceneConflictError(f"scan {scan_id!r} is already in the scene")
        origin, radius = bounding_sphere(scan, params)  # NumPy only: no kernel here
        return origin.tolist(), float(radius)

    def _stage(
        self, scene_id: str, scan_id: str, scan: Scan, name: str | None, origin: list[float],
        radius: float,
    ) -> PendingScan:  # fmt: skip
        entry = self._archive(scene_id).stage(scan_id, scan, name)
        return PendingScan(
            scene_id, scan_id, name, origin, radius, scan.far_ranges, scan.sensor.to_dict(),
            entry,
        )  # fmt: skip

    def stage_scan(
        self, scene_id: str, scan_id: str, scan: Scan, name: str | None = None
    ) -> PendingScan:
        """Write a scan into its scene's archive, not yet durable nor visible: the first half
        of storing it, which any thread may do (the service does it in the upload's request
        thread); :meth:`commit_scans` makes it durable and visible, many at once, and
        :meth:`discard_scans` drops it. A process that dies in between leaves a temporary
        folder that :meth:`cleanup_uploads` removes.

        Raises
        ------
        StoreError
            For an unknown scene; :class:`SceneConflictError` for a scan id it holds.
        """
        return self._stage(scene_id, scan_id, scan, name, *self._check_new(scene_id, scan_id, scan))

    def commit_scans(self, pending: Sequence[PendingScan]) -> list[ScanRow | Exception]:
        """Make staged scans durable and visible with one round of fsyncs and one catalog
        transaction (a group commit). Returns, in order, each scan's row or the error that
        refused it; an error of the shared steps (a full disk) fails every scan, and nothing
        of them stays."""
        try:
            for archive, group in _by_archive([p.entry for p in pending]):
                archive.publish(group)
            with self.catalog.transaction():
                for p in pending:
                    self.catalog.add_scan(
                        p.scene_id, p.scan_id, p.name, p.origin, p.radius, p.entry.checksum,
                        p.far_ranges,
                    )  # fmt: skip
                    # a scene without a sensor of its own takes its first scan's
                    self.catalog.set_scene_sensor(p.scene_id, p.sensor, True)
        except Exception as exc:
            self.discard_scans(pending)
            for p in pending:
                with contextlib.suppress(Exception):
                    self._archive(p.scene_id).delete(p.scan_id)
            return [exc for _ in pending]
        rows: list[ScanRow | Exception] = []
        for p in pending:
            row = self.catalog.scan(p.scene_id, p.scan_id)
            rows.append(row if row is not None else StoreError(f"scan {p.scan_id!r} vanished"))
        return rows

    @staticmethod
    def discard_scans(pending: Sequence[PendingScan]) -> None:
        """Remove staged scans that will not be committed."""
        for p in pending:
            p.entry.discard()

    def _archive(self, scene_id: str) -> ScanArchive:
        return ScanArchive(self.scene_path(scene_id) / "scene.zarr")

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

    def lock_scene(self, scene_id: str, wait: bool = False) -> int:
        """Take the scene's writer lock (waiting for it with ``wait``); returns the lock's
        file descriptor, whose closing releases it.

        Raises
        ------
        StoreLockedError
            When another process holds it and ``wait`` is false.
        """
        self.scene_spec(scene_id)  # the scene exists
        return _lock_scene(self.scene_path(scene_id), wait=wait)


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


def _write_marker(path: Path) -> None:
    """Write the layout marker durably (last, when a store is created)."""
    tmp = path / f".{_MARKER}.tmp"
    tmp.write_text(json.dumps({"format": "rangefuse-store", "version": STORE_VERSION}))
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path / _MARKER)
    fsync_path(path)


def check_same(path: Path, what: str, stored: dict[str, Any], given: Any) -> None:
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


#: A scan to store: ``(scene_id, scan_id, scan, name)``.
NewScan = tuple[str, str, Scan, "str | None"]


def _by_archive(entries: list[StagedScan]) -> Iterator[tuple[ScanArchive, list[StagedScan]]]:
    """Staged entries grouped by the archive (scene) they belong to."""
    groups: dict[Path, list[StagedScan]] = {}
    for entry in entries:
        groups.setdefault(entry.final.parent, []).append(entry)
    for scans_dir, group in groups.items():
        yield ScanArchive(scans_dir.parent), group
