"""The catalog's rows of tiles (version 3, docs/storage.md "Catalog version 3"): a row per
tile, ``owners`` (how many scans own it) and ``scans``, a blob of the tile's entries
``2 * scan number + owner`` as little-endian int64, sorted by scan number."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Iterator, Mapping, Sequence

import numpy as np

__all__ = [
    "ENTRY",
    "MERGE_PAIRS",
    "MERGE_TILES",
    "entries",
    "flat",
    "merge",
    "merged",
    "read_rows",
    "remove_scan",
    "rows_of_runs",
    "write_rows",
]

ENTRY = np.dtype("<i8")
#: (scan, tile) pairs a checkpoint merges into the rows at once: 2^21, 32 MB of keys and
#: entries (a 1 cm scan of a street has about 300,000)...
MERGE_PAIRS = 2**21
#: ... and tiles whose rows it reads and rewrites at once: their entries are about 40 per
#: tile on a long drive (20 MB).
MERGE_TILES = 2**16


def entries(blob: bytes) -> np.ndarray:
    """A row's entries (read-only)."""
    return np.frombuffer(blob, ENTRY)


def flat(rows: Mapping[int, bytes]) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``{tile: blob}`` as pairs: each entry with its tile."""
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    blobs = list(rows.values())
    counts = np.fromiter((len(b) // ENTRY.itemsize for b in blobs), np.int64, len(blobs))
    tiles = np.repeat(np.fromiter(rows.keys(), np.int64, len(rows)), counts)
    return tiles, np.frombuffer(b"".join(blobs), ENTRY).astype(np.int64)


def rows_of_runs(tiles: np.ndarray, values: np.ndarray) -> Iterator[tuple[int, int, bytes]]:
    """``(tile, owners, blob)`` for each run of one tile in ``tiles`` (sorted), its entries
    ``values`` in the order given."""
    if len(tiles) == 0:
        return
    starts = np.flatnonzero(np.r_[True, tiles[1:] != tiles[:-1]])
    owners = np.add.reduceat(values & 1, starts).tolist()
    data = values.astype(ENTRY).tobytes()
    ends = (np.r_[starts[1:], len(tiles)] * ENTRY.itemsize).tolist()
    begins = (starts * ENTRY.itemsize).tolist()
    for tile, n, a, b in zip(tiles[starts].tolist(), owners, begins, ends, strict=True):
        yield tile, n, data[a:b]


def merged(
    tiles: np.ndarray, values: np.ndarray, old: Mapping[int, bytes]
) -> Iterator[tuple[int, int, bytes]]:
    """The rows of the tiles of the pairs ``(tiles, values)`` (packed keys and entries) merged
    into their ``old`` rows: a pair replaces its tile's entry for the same scan, a later
    pair an earlier one."""
    old_tiles, old_values = flat(old)
    t = np.concatenate([old_tiles, np.asarray(tiles, np.int64)])
    v = np.concatenate([old_values, np.asarray(values, np.int64)])
    order = np.lexsort((v >> 1, t))  # stable: old entries first, then the pairs in order
    t, v = t[order], v[order]
    last = np.r_[(t[1:] != t[:-1]) | ((v[1:] >> 1) != (v[:-1] >> 1)), True]
    return rows_of_runs(t[last], v[last])


def read_rows(db: sqlite3.Connection, scene: int, tiles: Sequence[int]) -> dict[int, bytes]:
    """``{tile: scans}`` of the rows there are among the packed keys ``tiles`` of the scene
    numbered ``scene``."""
    out: dict[int, bytes] = {}
    for start in range(0, len(tiles), 500):
        chunk = list(tiles[start : start + 500])
        marks = ",".join("?" * len(chunk))
        out.update(
            db.execute(
                f"SELECT tile, scans FROM tile_scans WHERE scene=? AND tile IN ({marks})",
                (scene, *chunk),
            ).fetchall()
        )
    return out


def write_rows(db: sqlite3.Connection, scene: int, rows: Iterable[tuple[int, int, bytes]]) -> None:
    """Write the rows ``(tile, owners, scans)`` of the scene numbered ``scene``."""
    db.executemany(
        "INSERT OR REPLACE INTO tile_scans(scene, tile, owners, scans) VALUES(?,?,?,?)",
        ((scene, tile, owners, blob) for tile, owners, blob in rows),
    )


def remove_scan(
    db: sqlite3.Connection, scene: int, scan: int, ranges: Sequence[tuple[int, int]] | None
) -> None:
    """Take the scan numbered ``scan`` out of the rows in the packed-key ranges ``[lo, hi]``
    (or all the scene's rows); a row left without entries goes."""
    sql = "SELECT tile, scans FROM tile_scans WHERE scene=?"
    queries = [(sql, (scene,))] if ranges is None else [
        (sql + " AND tile BETWEEN ? AND ?", (scene, int(lo), int(hi))) for lo, hi in ranges
    ]  # fmt: skip
    rows: list[tuple[int, int, bytes]] = []
    gone: list[tuple[int, int]] = []
    for query, args in queries:
        for tile, blob in db.execute(query, args).fetchall():
            e = entries(blob)
            keep = (e >> 1) != scan
            if keep.all():
                continue
            if keep.any():
                rows.append((tile, int((e[keep] & 1).sum()), e[keep].tobytes()))
            else:
                gone.append((scene, tile))
    write_rows(db, scene, rows)
    db.executemany("DELETE FROM tile_scans WHERE scene=? AND tile=?", gone)


def merge(
    db: sqlite3.Connection, scene: int, tiles: list[np.ndarray], values: list[np.ndarray]
) -> None:
    """Merge pairs (packed keys ``tiles`` and entries ``values``, in order) into their
    tiles' rows, :data:`MERGE_TILES` tiles at a time (their rows' entries, read and
    rewritten, are what a merge holds besides the pairs)."""
    t, v = np.concatenate(tiles), np.concatenate(values)
    order = np.argsort(t, kind="stable")  # a scan's later pair stays after its earlier
    t, v = t[order], v[order]
    del order
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
    for first in range(0, len(starts), MERGE_TILES):
        a = starts[first]
        b = starts[first + MERGE_TILES] if first + MERGE_TILES < len(starts) else len(t)
        old = read_rows(db, scene, t[starts[first : first + MERGE_TILES]].tolist())
        write_rows(db, scene, merged(t[a:b], v[a:b], old))
