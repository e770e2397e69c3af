"""Where units of work write their tiles until a checkpoint publishes them (docs/storage.md,
"Units that can run again").

A unit never writes a scene's committed chunks: it reads them, and writes each tile it
changes here, under ``<scene>/staging/c/<i>/<j>/<k>`` (the chunk's own name and bytes; a
tile that became all unknown is an empty file, a *tombstone*). A unit killed at any point
and run again therefore starts from the same committed state and writes the same bytes.
Once the catalog has committed a group's checkpoint, :meth:`Staging.publish` moves the
staged chunks over the committed ones (and deletes the tombstoned ones); it is idempotent,
so a publish cut short is finished at the next open. Without a committed checkpoint, the
staged chunks are discarded.

Each chunk is written to a temporary file and renamed, as zarr's ``LocalStore`` does, so a
staged chunk is never torn; paths are plain strings and each folder is made once (per
chunk, ``pathlib`` and a ``mkdir`` cost as much as the write itself).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .zarr_tiles import (
    KEY_OFFSET,
    TileArrayError,
    ZarrTiles,
    fsync_paths,
    stored_chunk_keys,
    tile_rows,
)

__all__ = ["Staging"]


class Staging:
    """The staging area of one scene, for the chunks of its tile array ``tiles``."""

    def __init__(self, folder: Path, tiles: ZarrTiles) -> None:
        self.folder = Path(folder)
        self.tiles = tiles
        self._made: set[str] = set()  # folders known to exist
        # temporary files are <chunk>.<token><n>.partial: unique to this object (a unit run
        # twice at once writes beside itself), without a uuid4 per chunk (10 us each)
        self._token = uuid.uuid4().hex
        self._serial = 0

    def _names(self, keys: np.ndarray) -> list[str]:
        return [f"c/{i}/{j}/{k}" for i, j, k in (keys + KEY_OFFSET).tolist()]

    def _folder(self, path: str) -> None:
        folder = os.path.dirname(path)
        if folder not in self._made:
            os.makedirs(folder, exist_ok=True)
            self._made.add(folder)

    def _put(self, path: str, payload: bytes) -> None:
        """Write ``path`` through a temporary file and a rename (never torn)."""
        self._folder(path)
        self._serial += 1
        tmp = f"{path}.{self._token}{self._serial}.partial"
        try:
            with open(tmp, "wb") as fh:
                fh.write(payload)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    def write(self, keys: np.ndarray, data: Sequence[np.ndarray]) -> None:
        """Stage whole tiles (each int64 (T, T, T): an (n, T, T, T) array or a list of the
        cache's tiles, which need no copy into one array); an all-unknown tile as a
        tombstone."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        root = str(self.folder)
        for tile, name in zip(data, self._names(keys), strict=True):
            self._put(f"{root}/{name}", self.tiles.encode(tile) if tile.any() else b"")

    def delete(self, keys: np.ndarray) -> None:
        """Stage the deletion of tiles (tombstones)."""
        root = str(self.folder)
        for name in self._names(np.asarray(keys, np.int64).reshape(-1, 3)):
            self._put(f"{root}/{name}", b"")

    def read(
        self, keys: np.ndarray, out: np.ndarray | None = None, rows: np.ndarray | None = None
    ) -> np.ndarray:
        """Staged tiles (they must have been staged); a tombstone reads as unknown. ``out``
        and ``rows`` as in :meth:`ZarrTiles.read`."""
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        out, flat, at = tile_rows(out, rows, len(keys), self.tiles.tile_size)
        root = str(self.folder)
        for n, name in enumerate(self._names(keys)):
            path = f"{root}/{name}"
            try:
                with open(path, "rb") as fh:
                    raw = fh.read()
            except FileNotFoundError:
                raise TileArrayError(f"tile {keys[n].tolist()} was not staged") from None
            if raw:
                flat[at[n]] = self.tiles.decode(raw, f"staged tile {keys[n].tolist()}: {path}")
            else:
                flat[at[n]] = 0
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
        durable, then empty the staging area. Idempotent; returns the tiles published.

        A staged folder ``c/<i>/<j>`` whose committed twin does not exist yet (new ground)
        moves whole, its tombstones dropped first; in a committed folder, chunk by chunk.
        """
        keys = self.staged_keys()
        live_c = str(self.tiles.path / "c")
        staged_c = str(self.folder / "c")
        for i, j in np.unique(keys[:, :2] + KEY_OFFSET, axis=0).tolist():
            staged = f"{staged_c}/{i}/{j}"
            live = f"{live_c}/{i}/{j}"
            entries = list(os.scandir(staged))
            chunks = [e for e in entries if e.name.isdigit()]
            if not os.path.isdir(live):
                for entry in entries:  # tombstones (nothing committed to delete), orphans
                    if not entry.name.isdigit() or entry.stat().st_size == 0:
                        os.unlink(entry.path)
                os.makedirs(f"{live_c}/{i}", exist_ok=True)
                os.replace(staged, live)
                continue
            for entry in chunks:
                target = f"{live}/{entry.name}"
                if entry.stat().st_size == 0:
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(target)
                    os.unlink(entry.path)
                else:
                    os.replace(entry.path, target)
        if len(keys):
            self.tiles.fsync(keys)
        self.discard()
        return len(keys)

    def discard(self) -> None:
        """Drop whatever is staged (a group that was never committed)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        self._made.clear()
