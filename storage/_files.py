"""Writing files so that a crash never leaves a half-written one behind."""

from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: Path, write: Callable[[BinaryIO], object], fsync: bool = False) -> None:
    """Write ``path`` through a temporary file in the same folder and a rename.

    With ``fsync`` the data and the folder entry are flushed to disk before returning.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; files get the usual mode
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if fsync:
        fsync_path(path.parent)


def fsync_paths(paths: Sequence[Path]) -> None:
    """fsync many files and folders side by side (threads): the file system can join their
    journal commits, which one after the other costs a commit each."""
    if len(paths) <= 1:
        for path in paths:
            fsync_path(path)
        return
    list(_fsync_pool().map(fsync_path, paths))


_POOL_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None


def _fsync_pool() -> ThreadPoolExecutor:
    """The process's threads for :func:`fsync_paths`, started once (starting 16 threads for
    each batch of uploads cost more than their fsyncs)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(16, thread_name_prefix="rangefuse-fsync")
        return _POOL


def fsync_path(path: Path) -> None:
    """fsync a file or a folder (a folder: its entries, created, renamed or deleted)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _read_umask() -> int:
    mask = os.umask(0o022)  # the only way to read it; once, at import (not thread-safe)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write_text(path: Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    data = text.encode()
    atomic_write(path, lambda fh: fh.write(data))
