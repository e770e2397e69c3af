"""Where units of work write their tiles until a checkpoint publishes them (docs/storage.md,
"Units that can run again").

A unit never writes a scene's committed chunks: it reads them, and writes each tile it
changes here, under ``<scene>/staging/c/<i>/<j>/<k>`` (the chunk's own name and bytes; a
tile that became all unknown is an empty file, a *tombstone*). A unit killed at any point
and run again therefore starts from the same committed state and writes the same bytes.
Once the catalog has committed a group's checkpoint, :meth:`Staging.publish` renames the
staged chunks over the committed ones (and deletes the tombstoned ones); it is idempotent,
so a publish cut short is finished at the next open. Without a committed checkpoint, the
staged chunks are discarded.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import numpy as np
from zarr.core.buffer import default_buffer_prototype
from zarr.storage import LocalStore

from .zarr_tiles import KEY_OFFSET, TileArrayError, ZarrTiles, fsync_paths, stored_chunk_keys

__all__ = ["Staging"]


class Staging:
    """The staging area of one scene, for the chunks of its tile array ``tiles``."""

    def __init__(self, folder: Path, tiles: ZarrTiles) -> None:
        self.folder = Path(folder)
        self.tiles = tiles
        self._store = LocalStore(self.folder)  # temporary file then rename: never torn
        self._prototype = default_buffer_prototype()

    def _names(self, keys: np.ndarray) -> list[str]:
        return [f"c/{i}/{j}/{k}" for i, j, k in (keys + KEY_OFFSET).tolist()]

    def write(self, keys: np.ndarray, data: np.ndarray) -> None:
        """Stage whole tiles (int64 (n, T, T, T)); an all-unknown tile as a tombstone."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        for tile, name in zip(data, self._names(keys), strict=True):
            payload = self.tiles.encode(tile) if tile.any() else b""
            self._store.set_sync(name, self._prototype.buffer.from_bytes(payload))

    def delete(self, keys: np.ndarray) -> None:
        """Stage the deletion of tiles (tombstones)."""
        for name in self._names(np.asarray(keys, np.int64).reshape(-1, 3)):
            self._store.set_sync(name, self._prototype.buffer.from_bytes(b""))

    def read(self, keys: np.ndarray) -> np.ndarray:
        """Staged tiles (they must have been staged); a tombstone reads as unknown."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        T = self.tiles.tile_size
        out = np.zeros((len(keys), T, T, T), np.int64)
        flat = out.reshape(len(keys), T**3)
        for n, name in enumerate(self._names(keys)):
            path = self.folder / name
            try:
                raw = path.read_bytes()
            except FileNotFoundError:
                raise TileArrayError(f"tile {keys[n].tolist()} was not staged") from None
            if raw:
                flat[n] = self.tiles.decode(raw, f"staged tile {keys[n].tolist()}: {path}")
        return out

    def fsync(self, keys: np.ndarray) -> None:
        """Make the staged state of ``keys`` durable."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        fsync_paths(self.folder, self._names(keys))

    def staged_keys(self) -> np.ndarray:
        """Keys of every staged chunk and tombstone (sorted int64 (n, 3))."""
        return stored_chunk_keys(self.folder / "c")

    def publish(self) -> int:
        """Move every staged chunk over the committed one (a tombstone deletes it), make that
        durable, then empty the staging area. Idempotent; returns the tiles published."""
        keys = self.staged_keys()
        for key, name in zip(keys, self._names(keys), strict=True):
            staged = self.folder / name
            live = self.tiles.chunk_path(key)
            if staged.stat().st_size == 0:
                with contextlib.suppress(FileNotFoundError):
                    live.unlink()
                staged.unlink()
            else:
                live.parent.mkdir(parents=True, exist_ok=True)
                os.replace(staged, live)
        if len(keys):
            self.tiles.fsync(keys)
        self.discard()
        return len(keys)

    def discard(self) -> None:
        """Drop whatever is staged (a group that was never committed)."""
        shutil.rmtree(self.folder, ignore_errors=True)
