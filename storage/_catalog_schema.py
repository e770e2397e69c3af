"""The catalog's tables (docs/storage.md, "Catalog (SQLite)") and the upgrades of a catalog
written by an older rangefuse: columns added since, and version 1's ``tile_scans``."""

from __future__ import annotations

import sqlite3

__all__ = ["SCHEMA", "add_columns", "upgrade_from_1"]

_TILE_SCANS = """
CREATE TABLE IF NOT EXISTS tile_scans(
    scene INTEGER NOT NULL, tile INTEGER NOT NULL, scan INTEGER NOT NULL,
    owner INTEGER NOT NULL, PRIMARY KEY(scene, tile, scan)) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS tile_scans_scan ON tile_scans(scene, scan);
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
{_TILE_SCANS.strip()}
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


#: Version 1's rows rewritten with numbers (run after the version-2 table is made).
_FROM_1 = (
    "INSERT OR IGNORE INTO scene_nums(id) SELECT DISTINCT scene_id FROM tile_scans_v1",
    "INSERT INTO scan_nums(scene, id) SELECT DISTINCT n.num, v.scan_id "
    "FROM tile_scans_v1 v JOIN scene_nums n ON n.id = v.scene_id",
    "INSERT INTO tile_scans(scene, tile, scan, owner) "
    "SELECT n.num, v.tile, m.num, v.owner FROM tile_scans_v1 v "
    "JOIN scene_nums n ON n.id = v.scene_id "
    "JOIN scan_nums m ON m.scene = n.num AND m.id = v.scan_id",
    "DROP TABLE tile_scans_v1",
)


def upgrade_from_1(db: sqlite3.Connection, version: int) -> None:
    """Rewrite a version-1 ``tile_scans`` (the scene's and the scan's ids as text in every
    row) with numbers and make the catalog ``version``, in one transaction (a crash
    leaves version 1). ``db`` is in autocommit mode, outside a transaction."""
    db.execute("BEGIN IMMEDIATE")
    try:
        row = db.execute("SELECT value FROM meta WHERE key='version'").fetchone()
        if row[0] == "1":  # not upgraded by another process meanwhile
            db.execute("INSERT OR IGNORE INTO scene_nums(id) SELECT id FROM scenes")
            columns = {r[1] for r in db.execute("PRAGMA table_info(tile_scans)")}
            if "scene_id" in columns:  # version 1's table (not one this open just made)
                db.execute("DROP INDEX IF EXISTS tile_scans_scan")
                db.execute("ALTER TABLE tile_scans RENAME TO tile_scans_v1")
                for statement in [*_TILE_SCANS.split(";"), *_FROM_1]:
                    if statement.strip():
                        db.execute(statement)
            db.execute("UPDATE meta SET value=? WHERE key='version'", (str(version),))
    except BaseException:
        db.execute("ROLLBACK")
        raise
    db.execute("COMMIT")
