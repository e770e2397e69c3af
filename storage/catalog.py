"""The catalog: scenes, scans, which scans inform which tiles, tile journal, epochs, mesh cache.

One SQLite file per store (``docs/storage.md``), opened in WAL mode with
``synchronous=FULL``: a committed transaction survives a kill -9 and a power loss. Tiles
are identified by their packed key (:func:`engine.grid.pack_keys`). The service keeps its
own tables (tokens, idempotency keys, jobs, meshes of reconstructions) in the same file,
through its own connection (``service/accounts.py``, ``service/queue.py``).
"""

from __future__ import annotations

import errno
import json
import os
import sqlite3
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from . import _tile_rows
from ._catalog_schema import SCHEMA, add_columns, upgrade
from ._tile_rows import entries, merged, read_rows, remove_scan, write_rows

__all__ = [
    "CATALOG_VERSION",
    "Catalog",
    "CatalogError",
    "ScanRow",
    "SceneRow",
]

#: Version 3 (docs/storage.md, "Catalog version 3"): ``tile_scans`` holds a row per tile,
#: its scans' numbers (``scan_nums``) and owner flags in one blob; version 2 held a row per
#: (scan, tile) pair, version 1 the same with the ids' text. Both are upgraded when opened.
CATALOG_VERSION = 3
#: SQLite's page cache per connection (KiB).
_CACHE_KIB = 16384
#: Bytes of write-ahead log SQLite leaves on disk once it is checkpointed: a group's
#: transaction (a row per tile it touches) would otherwise keep its log's size beside the
#: catalog for good.
WAL_LIMIT = 8 * 2**20

#: States of a scan: archived and acknowledged; fused into the tiles; being removed.
SCAN_STATES = ("stored", "fused", "removing")


class CatalogError(RuntimeError):
    """The catalog file is unusable (another layout version, not a catalog)."""


@dataclass(frozen=True)
class SceneRow:
    id: str
    name: str
    tenant: str
    grid: dict[str, Any]
    params: dict[str, Any]
    created_at: float
    #: The scene's default sensor (``Sensor.to_dict``): given when the scene was created or
    #: taken from its first stored scan; None until then.
    sensor: dict[str, Any] | None = None


@dataclass(frozen=True)
class ScanRow:
    id: str
    seq: int
    name: str | None
    state: str
    origin: tuple[float, float, float]
    reach_m: float
    checksum: str
    created_at: float
    #: Finite ranges beyond the sensor's max_range, set invalid when the scan was decoded
    #: (None: stored before the catalog counted them).
    far_ranges: int | None = None


_Item = TypeVar("_Item")


def _packed(tiles: np.ndarray | Sequence[int]) -> list[int]:
    return [int(t) for t in np.asarray(tiles, np.int64).reshape(-1)]


def _no_room(path: Path) -> bool:
    """Whether the disk of ``path`` has less room than SQLite needs to open a database (its
    shared-memory file, a page or two of its log)."""
    try:
        st = os.statvfs(path.parent)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 2**20


class Catalog:
    """The SQLite catalog of a store. Not shared between threads; one writer process."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute(f"PRAGMA cache_size=-{_CACHE_KIB}")
            self._db.execute(f"PRAGMA journal_size_limit={int(WAL_LIMIT)}")
            self._db.executescript(SCHEMA)
            add_columns(self._db)
            row = self._db.execute("SELECT value FROM meta WHERE key='version'").fetchone()
        except sqlite3.DatabaseError as exc:
            if hasattr(self, "_db"):
                self._db.close()
            if _no_room(self.path):  # SQLite cannot make its shared-memory file: "I/O error"
                raise OSError(errno.ENOSPC, f"{self.path}: cannot open the catalog: the disk "
                              f"is full ({exc})") from None  # fmt: skip
            raise CatalogError(f"{self.path}: not a rangefuse catalog ({exc})") from None
        self._depth = 0
        self._nums: dict[str, int] = {}
        if row is None:
            self._db.execute(
                "INSERT INTO meta(key, value) VALUES('version', ?)", (str(CATALOG_VERSION),)
            )
        elif row[0] in ("1", "2"):
            try:
                upgrade(self._db, CATALOG_VERSION)
            except sqlite3.DatabaseError as exc:
                self._db.close()
                raise CatalogError(
                    f"{self.path}: upgrading the catalog from version {row[0]} to "
                    f"{CATALOG_VERSION} failed ({exc}); it is left at version {row[0]}"
                ) from None
        elif row[0] != str(CATALOG_VERSION):
            self._db.close()
            raise CatalogError(
                f"{self.path}: catalog version {row[0]}, this rangefuse reads versions 1 "
                f"and 2 (upgraded when opened) and {CATALOG_VERSION}"
            )

    def _num(self, scene_id: str, create: bool = False) -> int:
        """The scene's number in ``tile_scans``, given on its first row (without ``create``,
        -1, which matches no row, for a scene that has none)."""
        num = self._nums.get(scene_id)
        if num is None:
            if create:
                self._db.execute("INSERT OR IGNORE INTO scene_nums(id) VALUES(?)", (scene_id,))
            row = self._db.execute("SELECT num FROM scene_nums WHERE id=?", (scene_id,))
            found = row.fetchone()
            if found is None:
                return -1
            num = self._nums[scene_id] = int(found[0])
        return num

    def _scan_nums(self, scene: int, scan_ids: Sequence[str]) -> dict[str, int]:
        """``{scan_id: number}`` of the scans (any tile owner's id, whether or not it is a
        row of ``scans``) in ``tile_scans`` rows of the scene numbered ``scene``; given on
        first use."""
        wanted = sorted(set(scan_ids))
        self._db.executemany(
            "INSERT OR IGNORE INTO scan_nums(scene, id) VALUES(?,?)",
            [(scene, scan_id) for scan_id in wanted],
        )
        out: dict[str, int] = {}
        for chunk in _chunks(wanted, 500):
            marks = ",".join("?" * len(chunk))
            out.update(
                self._db.execute(
                    f"SELECT id, num FROM scan_nums WHERE scene=? AND id IN ({marks})",
                    (scene, *chunk),
                ).fetchall()
            )
        return out

    def close(self) -> None:
        self._db.close()

    # --- transactions -------------------------------------------------------------------------
    @contextmanager
    def transaction(self) -> Iterator[None]:
        """Everything inside commits together (nested uses join the outer one)."""
        if self._depth:
            self._depth += 1
            try:
                yield
            finally:
                self._depth -= 1
            return
        self._db.execute("BEGIN IMMEDIATE")
        self._depth = 1
        try:
            yield
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        else:
            self._db.execute("COMMIT")
        finally:
            self._depth = 0

    # --- scenes -------------------------------------------------------------------------------
    def create_scene(
        self,
        scene_id: str,
        name: str,
        tenant: str,
        grid: dict[str, Any],
        params: dict[str, Any],
        sensor: dict[str, Any] | None = None,
    ) -> SceneRow:
        now = time.time()
        self._db.execute(
            "INSERT INTO scenes(id, name, tenant, grid, params, created_at, sensor) "
            "VALUES(?,?,?,?,?,?,?)",
            (scene_id, name, tenant, json.dumps(grid), json.dumps(params), now, _json(sensor)),
        )
        return SceneRow(scene_id, name, tenant, grid, params, now, sensor)

    _SCENE_COLUMNS = "id, name, tenant, grid, params, created_at, sensor"

    def scene(self, scene_id: str) -> SceneRow | None:
        row = self._db.execute(
            f"SELECT {self._SCENE_COLUMNS} FROM scenes WHERE id=?", (scene_id,)
        ).fetchone()
        return None if row is None else self._scene_row(row)

    def set_scene_sensor(
        self, scene_id: str, sensor: dict[str, Any], only_if_none: bool = False
    ) -> bool:
        """Make ``sensor`` (``Sensor.to_dict``) the scene's default sensor; with
        ``only_if_none``, only when it has none yet. Returns whether the row changed."""
        sql = "UPDATE scenes SET sensor=? WHERE id=?"
        if only_if_none:
            sql += " AND sensor IS NULL"
        return self._db.execute(sql, (json.dumps(sensor), scene_id)).rowcount > 0

    def scenes(self, tenant: str | None = None) -> list[SceneRow]:
        sql = f"SELECT {self._SCENE_COLUMNS} FROM scenes"
        args: tuple[Any, ...] = ()
        if tenant is not None:
            sql += " WHERE tenant=?"
            args = (tenant,)
        return [self._scene_row(r) for r in self._db.execute(sql + " ORDER BY created_at", args)]

    @staticmethod
    def _scene_row(row: tuple[Any, ...]) -> SceneRow:
        sensor = None if row[6] is None else json.loads(row[6])
        return SceneRow(
            row[0], row[1], row[2], json.loads(row[3]), json.loads(row[4]), row[5], sensor
        )

    def delete_scene(self, scene_id: str) -> None:
        with self.transaction():
            num = self._num(scene_id)
            self._db.execute("DELETE FROM tile_scans WHERE scene=?", (num,))
            self._db.execute("DELETE FROM scan_nums WHERE scene=?", (num,))
            for table in ("scans", "journal", "publishing", "tile_epochs", "mesh_cache"):
                self._db.execute(f"DELETE FROM {table} WHERE scene_id=?", (scene_id,))
            self._db.execute("DELETE FROM scene_nums WHERE id=?", (scene_id,))
            self._db.execute("DELETE FROM scenes WHERE id=?", (scene_id,))
        self._nums.pop(scene_id, None)

    # --- scans --------------------------------------------------------------------------------
    def add_scan(
        self,
        scene_id: str,
        scan_id: str,
        name: str | None,
        origin: Sequence[float],
        reach_m: float,
        checksum: str,
        far_ranges: int | None = None,
    ) -> int:
        """Insert a scan in state ``stored``; returns its sequence number. ``far_ranges``:
        ranges beyond the sensor's max_range set invalid when it was decoded."""
        with self.transaction():
            row = self._db.execute(
                "SELECT COALESCE(MAX(seq), 0) + 1 FROM scans WHERE scene_id=?", (scene_id,)
            ).fetchone()
            seq = int(row[0])
            self._db.execute(
                "INSERT INTO scans(scene_id, id, seq, name, state, ox, oy, oz, reach_m, checksum,"
                " created_at, far_ranges) VALUES(?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    scene_id,
                    scan_id,
                    seq,
                    name,
                    "stored",
                    float(origin[0]),
                    float(origin[1]),
                    float(origin[2]),
                    float(reach_m),
                    checksum,
                    time.time(),
                    None if far_ranges is None else int(far_ranges),
                ),
            )
        return seq

    _SCAN_COLUMNS = "id, seq, name, state, ox, oy, oz, reach_m, checksum, created_at, far_ranges"

    @staticmethod
    def _scan_row(r: tuple[Any, ...]) -> ScanRow:
        return ScanRow(r[0], r[1], r[2], r[3], (r[4], r[5], r[6]), r[7], r[8], r[9], r[10])

    def scan(self, scene_id: str, scan_id: str) -> ScanRow | None:
        row = self._db.execute(
            f"SELECT {self._SCAN_COLUMNS} FROM scans WHERE scene_id=? AND id=?",
            (scene_id, scan_id),
        ).fetchone()
        return None if row is None else self._scan_row(row)

    def scans(self, scene_id: str, states: Sequence[str] | None = None) -> list[ScanRow]:
        """Scans in sequence order, optionally only those in ``states``."""
        rows = self._db.execute(
            f"SELECT {self._SCAN_COLUMNS} FROM scans WHERE scene_id=? ORDER BY seq", (scene_id,)
        )
        out = [self._scan_row(r) for r in rows]
        return out if states is None else [s for s in out if s.state in states]

    def n_scans(self, scene_id: str, states: Sequence[str]) -> int:
        """How many of the scene's scans are in ``states`` (a count, no rows read out)."""
        marks = ",".join("?" * len(states))
        row = self._db.execute(
            f"SELECT COUNT(*) FROM scans WHERE scene_id=? AND state IN ({marks})",
            (scene_id, *states),
        ).fetchone()
        return int(row[0])

    def scans_near_box(
        self,
        scene_id: str,
        lo_m: Sequence[float],
        hi_m: Sequence[float],
        slack_m: float,
        states: Sequence[str] = ("fused",),
    ) -> list[ScanRow]:
        """Scans in ``states`` whose bounding sphere (origin, ``reach_m``) may come within
        ``slack_m`` of the box ``[lo_m, hi_m]`` (metres), in sequence order: those whose
        origin lies in the box widened by the scene's largest finite reach and the slack, and
        those of unbounded reach. A superset of the spheres that meet the box (the caller
        tests each); found through the indexes on the origin's x and on the reach, not by
        reading every scan of the scene."""
        inf = float("inf")
        row = self._db.execute(
            "SELECT MAX(reach_m) FROM scans WHERE scene_id=? AND reach_m < ?", (scene_id, inf)
        ).fetchone()
        pad = (float(row[0]) if row[0] is not None else 0.0) + float(slack_m)
        lo = [float(x) - pad for x in lo_m]
        hi = [float(x) + pad for x in hi_m]
        marks = ",".join("?" * len(states))
        near = self._db.execute(
            f"SELECT {self._SCAN_COLUMNS} FROM scans WHERE scene_id=? AND ox BETWEEN ? AND ? "
            f"AND oy BETWEEN ? AND ? AND oz BETWEEN ? AND ? AND state IN ({marks})",
            (scene_id, lo[0], hi[0], lo[1], hi[1], lo[2], hi[2], *states),
        ).fetchall()
        unbounded = self._db.execute(
            f"SELECT {self._SCAN_COLUMNS} FROM scans WHERE scene_id=? AND reach_m >= ? "
            f"AND state IN ({marks})",
            (scene_id, inf, *states),
        ).fetchall()
        rows = {r[0]: self._scan_row(r) for r in [*near, *unbounded]}
        return sorted(rows.values(), key=lambda r: r.seq)

    def set_scan_state(self, scene_id: str, scan_ids: Sequence[str], state: str) -> None:
        if state not in SCAN_STATES:
            raise ValueError(f"unknown scan state {state!r}")
        self._db.executemany(
            "UPDATE scans SET state=? WHERE scene_id=? AND id=?",
            [(state, scene_id, s) for s in scan_ids],
        )

    def delete_scan(self, scene_id: str, scan_id: str) -> None:
        self._db.execute("DELETE FROM scans WHERE scene_id=? AND id=?", (scene_id, scan_id))

    # --- tiles --------------------------------------------------------------------------------
    # ``tile_scans`` rows are (scene number, packed tile key, owners, scans): a row per tile,
    # ``scans`` the entries ``2 * scan number + owner`` of the scans that inform or own it
    # (``storage._tile_rows``); a tile exists iff it has an owner.
    def tile_keys(self, scene_id: str) -> np.ndarray:
        """Packed keys of the tiles that exist (have an owner), sorted."""
        rows = self._db.execute(
            "SELECT tile FROM tile_scans WHERE scene=? AND owners>0 ORDER BY tile",
            (self._num(scene_id),),
        ).fetchall()
        return np.array([r[0] for r in rows], np.int64)

    def tile_keys_in_ranges(self, scene_id: str, ranges: Sequence[tuple[int, int]]) -> np.ndarray:
        """Packed keys of the tiles that exist within the packed-key ranges ``[lo, hi]``
        (ascending, disjoint), sorted: one range query on the tile index per range."""
        num = self._num(scene_id)
        out: list[int] = []
        for lo, hi in ranges:
            rows = self._db.execute(
                "SELECT tile FROM tile_scans WHERE scene=? AND tile BETWEEN ? AND ? "
                "AND owners>0 ORDER BY tile",
                (num, int(lo), int(hi)),
            ).fetchall()
            out.extend(r[0] for r in rows)
        return np.array(out, np.int64)

    def n_tiles(self, scene_id: str) -> int:
        row = self._db.execute(
            "SELECT COUNT(*) FROM tile_scans WHERE scene=? AND owners>0", (self._num(scene_id),)
        ).fetchone()
        return int(row[0])

    def tile_scans(self, scene_id: str, tiles: np.ndarray) -> dict[int, list[tuple[str, bool]]]:
        """``{tile: [(scan_id, is_owner), ...]}`` for the given packed keys."""
        num = self._num(scene_id)
        out: dict[int, list[tuple[str, bool]]] = {t: [] for t in _packed(tiles)}
        rows = {t: entries(b) for t, b in read_rows(self._db, num, list(out)).items()}
        nums = sorted({n for e in rows.values() for n in (e >> 1).tolist()})
        ids: dict[int, str] = {}
        for chunk in _chunks(nums, 500):
            marks = ",".join("?" * len(chunk))
            ids.update(
                self._db.execute(f"SELECT num, id FROM scan_nums WHERE num IN ({marks})", chunk)
            )
        for tile, e in rows.items():
            out[tile] = [
                (ids[n], bool(o)) for n, o in zip((e >> 1).tolist(), (e & 1).tolist(), strict=True)
            ]
        return out

    def add_tile_scans(
        self, scene_id: str, rows: Iterable[tuple[str, np.ndarray, np.ndarray]]
    ) -> None:
        """Record, per scan ``(scan_id, tiles, owner)``, the tiles (packed keys) it informs
        and whether it owns each (a scan's entry in a tile replaces the one it had): merged
        into the tiles' rows :data:`~storage._tile_rows.MERGE_PAIRS` pairs at a time."""
        num = self._num(scene_id, create=True)
        tiles: list[np.ndarray] = []
        values: list[np.ndarray] = []
        pending = 0
        for scan_id, scan_tiles, owner in rows:
            scan = self._scan_nums(num, [scan_id])[scan_id]
            scan_tiles = np.asarray(scan_tiles, np.int64).reshape(-1)
            owner = np.asarray(owner, np.bool_).reshape(-1)
            if len(owner) != len(scan_tiles):
                raise ValueError(f"{len(owner)} owner flags for {len(scan_tiles)} tiles")
            tiles.append(scan_tiles)
            values.append(2 * scan + owner.astype(np.int64))
            pending += len(scan_tiles)
            if pending >= _tile_rows.MERGE_PAIRS:
                _tile_rows.merge(self._db, num, tiles, values)
                tiles, values, pending = [], [], 0
        if pending:
            _tile_rows.merge(self._db, num, tiles, values)

    def remove_tile_scans(
        self, scene_id: str, scan_id: str, ranges: Sequence[tuple[int, int]] | None = None
    ) -> None:
        """Forget the scan's entries (and its number): in the rows of the packed-key ranges
        ``[lo, hi]`` (every tile the scan informs or owns lies in them), or of every tile."""
        num = self._num(scene_id)
        row = self._db.execute(
            "SELECT num FROM scan_nums WHERE scene=? AND id=?", (num, scan_id)
        ).fetchone()
        if row is None:
            return
        remove_scan(self._db, num, row[0], ranges)
        self._db.execute("DELETE FROM scan_nums WHERE num=?", (row[0],))

    def set_tile_owners(
        self, scene_id: str, tiles: np.ndarray, owners: Sequence[frozenset[str]]
    ) -> None:
        """Make ``owners[n]`` the owners of tile ``tiles[n]`` (packed keys); other scans that
        owned it keep an entry as informing scans."""
        num = self._num(scene_id, create=True)
        scans = self._scan_nums(num, [s for own in owners for s in own])
        packed = _packed(tiles)
        old = {t: (entries(b) & ~1).tobytes() for t, b in read_rows(self._db, num, packed).items()}
        pairs = [(t, 2 * scans[s] + 1) for t, own in zip(packed, owners, strict=True) for s in own]
        t = np.array([p[0] for p in pairs], np.int64)
        v = np.array([p[1] for p in pairs], np.int64)
        write_rows(self._db, num, merged(t, v, old))

    def delete_tiles(self, scene_id: str, tiles: np.ndarray) -> None:
        """Forget tiles (packed keys): every row of their owners and informing scans."""
        num = self._num(scene_id)
        self._db.executemany(
            "DELETE FROM tile_scans WHERE scene=? AND tile=?", [(num, t) for t in _packed(tiles)]
        )

    # --- journal and epochs -------------------------------------------------------------------
    def set_publishing(self, scene_id: str, attempt: str | None) -> None:
        """Record (or, with None, clear) that the chunks the attempt ``attempt`` staged belong
        to a committed checkpoint and are to be published (docs/storage.md)."""
        if attempt is None:
            self._db.execute("DELETE FROM publishing WHERE scene_id=?", (scene_id,))
        else:
            self._db.execute(
                "INSERT OR REPLACE INTO publishing(scene_id, attempt) VALUES(?,?)",
                (scene_id, attempt),
            )

    def publishing(self, scene_id: str) -> str | None:
        """The attempt whose staged chunks are to be published, if any."""
        row = self._db.execute(
            "SELECT attempt FROM publishing WHERE scene_id=?", (scene_id,)
        ).fetchone()
        return None if row is None else str(row[0])

    def journal(self, scene_id: str) -> np.ndarray:
        """Tiles a version-1 store had in flight when it was killed (that layout wrote tiles
        in place and journaled them first; the scene rebuilds them at its next open)."""
        rows = self._db.execute(
            "SELECT tile FROM journal WHERE scene_id=? ORDER BY tile", (scene_id,)
        ).fetchall()
        return np.array([r[0] for r in rows], np.int64)

    def journal_clear(self, scene_id: str) -> None:
        self._db.execute("DELETE FROM journal WHERE scene_id=?", (scene_id,))

    def bump_epochs(self, scene_id: str, tiles: np.ndarray) -> None:
        self._db.executemany(
            "INSERT INTO tile_epochs(scene_id, tile, epoch) VALUES(?,?,1) "
            "ON CONFLICT(scene_id, tile) DO UPDATE SET epoch = epoch + 1",
            [(scene_id, t) for t in _packed(tiles)],
        )

    def epochs(self, scene_id: str, tiles: np.ndarray) -> np.ndarray:
        keys = _packed(tiles)
        found: dict[int, int] = {}
        for chunk in _chunks(keys, 500):
            marks = ",".join("?" * len(chunk))
            for tile, epoch in self._db.execute(
                f"SELECT tile, epoch FROM tile_epochs WHERE scene_id=? AND tile IN ({marks})",
                (scene_id, *chunk),
            ):
                found[tile] = epoch
        return np.array([found.get(t, 0) for t in keys], np.int64)

    # --- mesh cache ---------------------------------------------------------------------------
    def mesh_cache_get(
        self, scene_id: str, tiles: np.ndarray, options: str
    ) -> dict[int, tuple[int, bytes]]:
        out: dict[int, tuple[int, bytes]] = {}
        for chunk in _chunks(_packed(tiles), 500):
            marks = ",".join("?" * len(chunk))
            for tile, epoch, data in self._db.execute(
                f"SELECT tile, epoch, data FROM mesh_cache WHERE scene_id=? AND options=? "
                f"AND tile IN ({marks})",
                (scene_id, options, *chunk),
            ):
                out[tile] = (epoch, data)
        return out

    def mesh_cache_put(
        self, scene_id: str, options: str, entries: Sequence[tuple[int, int, bytes]]
    ) -> None:
        with self.transaction():
            self._db.executemany(
                "INSERT OR REPLACE INTO mesh_cache(scene_id, tile, options, epoch, data) "
                "VALUES(?,?,?,?,?)",
                [(scene_id, int(t), options, int(e), d) for t, e, d in entries],
            )

    # --- sizes --------------------------------------------------------------------------------
    def counts(self) -> dict[str, Any]:
        """For metrics: scans by state, tiles."""
        scans = dict(
            self._db.execute("SELECT state, COUNT(*) FROM scans GROUP BY state").fetchall()
        )
        tiles = self._db.execute("SELECT COUNT(*) FROM tile_scans WHERE owners>0").fetchone()[0]
        return {"scans": scans, "tiles": int(tiles)}

    def count(self, table: str, scene_id: str) -> int:
        if table not in ("scans", "tile_scans", "journal", "mesh_cache"):
            raise ValueError(table)
        if table == "tile_scans":
            sql = "SELECT COUNT(*) FROM tile_scans WHERE scene=?"
            return int(self._db.execute(sql, (self._num(scene_id),)).fetchone()[0])
        return int(
            self._db.execute(
                f"SELECT COUNT(*) FROM {table} WHERE scene_id=?", (scene_id,)
            ).fetchone()[0]
        )


def _json(value: dict[str, Any] | None) -> str | None:
    return None if value is None else json.dumps(value)


def _chunks(items: list[_Item], n: int) -> Iterator[list[_Item]]:
    for start in range(0, len(items), n):
        yield items[start : start + n]
