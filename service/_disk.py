"""A full disk, recognised wherever it surfaces: ``OSError`` ENOSPC or EDQUOT from a file
write, or SQLite's "database or disk is full" from the catalog."""

from __future__ import annotations

import errno
import sqlite3

__all__ = ["DISK_FULL", "is_disk_full"]

#: What the service answers (HTTP 507) and a job records when the store's disk is full.
DISK_FULL = "the store's disk is full; nothing was stored: free space on it, then retry"


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from) means the disk is full."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(current, sqlite3.OperationalError) and "full" in str(current).lower():
            return True
        current = current.__cause__ or current.__context__
    return False
