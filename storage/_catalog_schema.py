"""The catalog's tables (docs/storage.md, "Catalog (SQLite)") and the upgrades of a catalog
written by an older rangefuse: columns added since, and the ``tile_scans`` of versions 1
and 2."""

from __future__ import annotations

import sqlite3

import numpy as np

from ._tile_rows import rows_of_runs

__all__ = ["SCHEMA", "add_columns", "upgrade"]

_TILE_SCANS = """
CREATE TABLE IF NOT EXISTS tile_scans(
    scene INTEGER NOT NULL, tile INTEGER NOT NULL, owners INTEGER NOT NULL,
    scans BLOB NOT NULL, PRIMARY KEY(scene, tile)) WITHOUT ROWID
"""
#: Version 2's table, under the name an upgrade reads it by.
_TILE_SCANS_2 = """
CREATE TABLE tile_scans_v2(
    scene INTEGER NOT NULL, tile INTEGER NOT NULL, scan INTEGER NOT NULL,
    owner INTEGER NOT NULL, PRIMARY KEY(scene, tile, scan)) WITHOUT ROWID
"""
SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS scenes(
    id TEXT PRIMARY KEY, name TEXT NOT NULL, tenant TEXT NOT NULL,
    grid TEXT NOT NULL, params TEXT NOT NULL, created_at REAL NOT NULL, sensor TEXT);
CREATE TABLE IF NOT EXISTS scans(
    scene_id TEXT NOT NULL, id TEXT NOT NULL, seq INTEGER NOT NULL, name TEXT,
    state TEXT NOT NULL, ox REAL NOT NULL, oy REAL NOT NULL, oz REAL NOT NULL,
    reach_m REAL NOT NULL, checksum TEXT NOT NULL, created_at REAL NOT NULL,
    far_ranges INTEGER, PRIMARY KEY(scene_id, id));
CREATE UNIQUE INDEX IF NOT EXISTS scans_seq ON scans(scene_id, seq);
CREATE INDEX IF NOT EXISTS scans_origin ON scans(scene_id, ox);
CREATE INDEX IF NOT EXISTS scans_reach ON scans(scene_id, reach_m);
CREATE TABLE IF NOT EXISTS scene_nums(num INTEGER PRIMARY KEY, id TEXT NOT NULL UNIQUE);
CREATE TABLE IF NOT EXISTS scan_nums(
    num INTEGER PRIMARY KEY, scene INTEGER NOT NULL, id TEXT NOT NULL, UNIQUE(scene, id));
{_TILE_SCANS.strip()};
CREATE TABLE IF NOT EXISTS journal(
    scene_id TEXT NOT NULL, tile INTEGER NOT NULL, PRIMARY KEY(scene_id, tile)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS publishing(scene_id TEXT PRIMARY KEY, attempt TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tile_epochs(
    scene_id TEXT NOT NULL, tile INTEGER NOT NULL, epoch INTEGER NOT NULL,
    PRIMARY KEY(scene_id, tile)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS mesh_cache(
    scene_id TEXT NOT NULL, tile INTEGER NOT NULL, options TEXT NOT NULL,
    epoch INTEGER NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY(scene_id, tile, options)) WITHOUT ROWID;
"""

#: Columns added after version 1 was released, ``(table, column, declaration)``: a catalog
#: written before them gains them when it is opened (NULL in its existing rows).
_ADDED_COLUMNS = (
    ("scenes", "sensor", "TEXT"),  # the scene's default sensor (JSON), if it has one
    ("scans", "far_ranges", "INTEGER"),  # ranges beyond max_range set invalid when decoded
)


def add_columns(db: sqlite3.Connection) -> None:
    """Give a catalog written before :data:`_ADDED_COLUMNS` those columns."""
    for table, column, declaration in _ADDED_COLUMNS:
        have = {r[1] for r in db.execute(f"PRAGMA table_info({table})")}
        if column not in have:
            try:
                db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")
            except sqlite3.OperationalError as exc:  # another process added it first
                if "duplicate column" not in str(exc):
                    raise


#: Version 1's rows rewritten with numbers into version 2's table (``tile_scans_v2``).
_FROM_1 = (
    "INSERT OR IGNORE INTO scene_nums(id) SELECT DISTINCT scene_id FROM tile_scans_v1",
    "INSERT INTO scan_nums(scene, id) SELECT DISTINCT n.num, v.scan_id "
    "FROM tile_scans_v1 v JOIN scene_nums n ON n.id = v.scene_id",
    "INSERT INTO tile_scans_v2(scene, tile, scan, owner) "
    "SELECT n.num, v.tile, m.num, v.owner FROM tile_scans_v1 v "
    "JOIN scene_nums n ON n.id = v.scene_id "
    "JOIN scan_nums m ON m.scene = n.num AND m.id = v.scan_id",
    "DROP TABLE tile_scans_v1",
)
#: Version 2's rows read at once while they are rewritten as version 3's.
_RUN = 2**20


def upgrade(db: sqlite3.Connection, version: int) -> None:
    """Rewrite the ``tile_scans`` of a version-1 catalog (the scene's and the scan's ids as
    text in a row per pair) or a version-2 one (numbers, a row per pair) as a row per tile
    and make the catalog ``version``, in one transaction (a crash leaves the old version).
    ``db`` is in autocommit mode, outside a transaction."""
    db.execute("BEGIN IMMEDIATE")
    try:
        (found,) = db.execute("SELECT value FROM meta WHERE key='version'").fetchone()
        columns = {r[1] for r in db.execute("PRAGMA table_info(tile_scans)")}
        if found in ("1", "2") and "owners" not in columns:  # not upgraded meanwhile
            db.execute("DROP INDEX IF EXISTS tile_scans_scan")
            if found == "1":
                db.execute("INSERT OR IGNORE INTO scene_nums(id) SELECT id FROM scenes")
                db.execute("ALTER TABLE tile_scans RENAME TO tile_scans_v1")
                db.execute(_TILE_SCANS_2)
                for statement in _FROM_1:
                    db.execute(statement)
            else:
                db.execute("ALTER TABLE tile_scans RENAME TO tile_scans_v2")
            db.execute(_TILE_SCANS)
            _from_2(db)
            db.execute("DROP TABLE tile_scans_v2")
        db.execute("UPDATE meta SET value=? WHERE key='version'", (str(version),))
    except BaseException:
        db.execute("ROLLBACK")
        raise
    db.execute("COMMIT")


def _from_2(db: sqlite3.Connection) -> None:
    """Version 2's rows (``tile_scans_v2``) written as version 3's, read in key order in
    runs of :data:`_RUN` (a tile's last rows wait for the next run)."""
    cursor = db.execute(
        "SELECT scene, tile, 2 * scan + owner FROM tile_scans_v2 ORDER BY scene, tile, scan"
    )
    held = np.zeros((0, 3), np.int64)
    while True:
        fetched = cursor.fetchmany(_RUN)
        run = np.concatenate([held, np.array(fetched, np.int64).reshape(-1, 3)])
        if fetched and len(run):  # the last (scene, tile) may go on in the next run
            same = (run[:, 0] == run[-1, 0]) & (run[:, 1] == run[-1, 1])
            run, held = run[~same], run[same]
        rows: list[tuple[int, int, int, bytes]] = []
        for scene in np.unique(run[:, 0]).tolist():
            mine = run[run[:, 0] == scene]
            rows.extend((scene, *row) for row in rows_of_runs(mine[:, 1], mine[:, 2]))
        db.executemany("INSERT INTO tile_scans(scene, tile, owners, scans) VALUES(?,?,?,?)", rows)
        if not fetched:
            return
