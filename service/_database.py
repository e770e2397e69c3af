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
    """The SQLite file at ``path`` with ``schema`` created; one connection per thread.

    Each thread that uses it opens its own connection on first use (as each thread of the
    API has its own :class:`~storage.Store`), so that readers never wait behind a writer
    (WAL) and no connection is shared between threads.
    """

    def __init__(self, path: Path, schema: str) -> None:
        self.path = Path(path)
        self._local = threading.local()
        self._opened: list[sqlite3.Connection] = []
        self._opened_lock = threading.Lock()
        self._connection().executescript(schema)

    def _connection(self) -> sqlite3.Connection:
        db: sqlite3.Connection | None = getattr(self._local, "db", None)
        if db is None:
            # check_same_thread=False only so that close() may close every thread's
            db = sqlite3.connect(
                self.path, isolation_level=None, timeout=30.0, check_same_thread=False
            )
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            self._local.db = db
            with self._opened_lock:
                self._opened.append(db)
        return db

    def close(self) -> None:
        """Close the connections of every thread."""
        with self._opened_lock:
            for db in self._opened:
                db.close()
            self._opened.clear()
        self._local = threading.local()

    def rows(self, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        """All rows of a query."""
        return self._connection().execute(sql, args).fetchall()

    def run(self, sql: str, args: tuple[Any, ...] = ()) -> int:
        """Execute a statement; the number of rows it changed."""
        return int(self._connection().execute(sql, args).rowcount)

    @contextmanager
    def transaction(self) -> Iterator[None]:
        """Everything this thread does inside commits together (not nested)."""
        db = self._connection()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            db.execute("ROLLBACK")
            raise
        else:
            db.execute("COMMIT")
