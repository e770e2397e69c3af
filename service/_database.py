"""The service's own tables in the store's SQLite file.

Storage's catalog (``storage/catalog.py``) holds what is on disk: scenes, scans, tiles.
The service keeps its tables (tokens and idempotency keys in :mod:`service.accounts`, jobs
and their meshes in :mod:`service.queue`) in the same file, ``catalog.sqlite`` of the
store, through a connection of its own opened the way the catalog opens its: WAL mode and
``synchronous=FULL``, so that a committed row survives a kill -9 and a power loss. Each
module creates its tables with ``CREATE TABLE IF NOT EXISTS``; stores written before the
tables moved already hold them, with the same columns.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["Database"]


class Database:
    """One SQLite connection that threads share (each use holds a lock)."""

    def __init__(self, path: Path, schema: str) -> None:
        self.path = Path(path)
        self._lock = threading.RLock()
        self._db = sqlite3.connect(
            self.path, isolation_level=None, timeout=30.0, check_same_thread=False
        )
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(schema)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def rows(self, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        """All rows of a query."""
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def run(self, sql: str, args: tuple[Any, ...] = ()) -> int:
        """Execute a statement; the number of rows it changed."""
        with self._lock:
            return int(self._db.execute(sql, args).rowcount)

    @contextmanager
    def transaction(self) -> Iterator[None]:
        """Everything this thread does inside commits together (other threads wait)."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            else:
                self._db.execute("COMMIT")
