"""Tiles in memory under a byte budget, for a unit of work (docs/storage.md, "Out of core").

A unit reads the scene's committed chunks and writes what it changes to the staging area
(:class:`~storage.staging.Staging`), never in place: evicted dirty tiles go there, and a tile
evicted earlier in the same unit is read back from there.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
from rangefuse.engine.grid import pack_keys, unpack_keys

from .staging import Staging
from .zarr_tiles import ZarrTiles

__all__ = ["TileCache", "cache_tiles"]


class TileCache:
    """Tiles in memory under a byte budget; dirty tiles are staged when evicted.

    Tiles are read from the committed chunks of ``tiles`` and written to ``staging``. The
    budget covers the resident tiles and the batch being worked on: the cache keeps at most
    3/4 of it in tiles, a batch is 1/4, and :meth:`store` keeps views of the caller's batch
    array instead of copies.
    """

    def __init__(self, tiles: ZarrTiles, staging: Staging, budget_bytes: int) -> None:
        self.tiles = tiles
        self.staging = staging
        self.T = tiles.tile_size
        self.capacity = cache_tiles(budget_bytes / 2**20, self.T)
        self._data: OrderedDict[int, np.ndarray] = OrderedDict()
        self._dirty: set[int] = set()
        self.written: set[int] = set()  # packed keys this cache has staged
        self.reads = 0
        self.writes = 0

    @property
    def batch(self) -> int:
        """Tiles one integration batch may hold (a third of the resident capacity)."""
        return max(4, self.capacity // 3)

    def fetch(self, keys: np.ndarray, new: np.ndarray) -> np.ndarray:
        """Copies of the tiles ``keys`` (int64 (n, 3)): as this cache holds or staged them,
        else committed; ``new`` ones start as unknown."""
        packed = pack_keys(keys)
        # zeros from calloc: pages of new tiles are first touched by the (parallel) kernel
        out = np.zeros((len(keys), self.T, self.T, self.T), np.int64)
        committed = []
        staged = []
        for n, p in enumerate(packed.tolist()):
            tile = self._data.get(p)
            if tile is not None:
                self._data.move_to_end(p)
                out[n] = tile
            elif p in self.written:  # evicted earlier: staged by this cache
                staged.append(n)
            elif not new[n]:
                committed.append(n)
        for rows, source in ((committed, self.tiles), (staged, self.staging)):
            if rows:
                picked = np.array(rows, np.int64)
                source.read(keys[picked], out, picked)
                self.reads += len(picked)
        return out

    def store(self, keys: np.ndarray, data: np.ndarray) -> None:
        """Put updated tiles back (dirty); evicts the least recently used beyond capacity."""
        for p, tile in zip(pack_keys(keys).tolist(), data, strict=True):
            self._data[p] = tile  # a view: the batch array lives while a tile of it is cached
            self._data.move_to_end(p)
            self._dirty.add(p)
        self._evict()

    def _evict(self) -> None:
        if len(self._data) <= self.capacity:
            return
        victims = []
        while len(self._data) > self.capacity * 3 // 4:
            p, tile = self._data.popitem(last=False)
            if p in self._dirty:
                victims.append((p, tile))
                self._dirty.discard(p)
        self._write(victims)

    def _write(self, items: list[tuple[int, np.ndarray]]) -> None:
        if not items:
            return
        packed = np.array([p for p, _ in items], np.int64)
        self.staging.write(unpack_keys(packed), [t for _, t in items])  # the tiles, not a copy
        self.written.update(packed.tolist())
        self.writes += len(items)

    def flush(self) -> None:
        """Stage every dirty tile."""
        self._write([(p, self._data[p]) for p in sorted(self._dirty)])
        self._dirty.clear()


def cache_tiles(cache_mb: float, tile_size: int) -> int:
    """Tiles a cache of ``cache_mb`` holds (see :class:`TileCache`)."""
    return max(8, int(cache_mb * 2**20) // (tile_size**3 * 8) * 3 // 4)
