"""A scene's tiles on disk as an engine :class:`~engine.volume.TileStore`.

:class:`ZarrTileStore` keeps voxel data in the scene's Zarr tile array
(:class:`~storage.zarr_tiles.ZarrTiles`, one chunk per tile) and owners in the catalog
(the entries of ``tile_scans`` rows with the owner flag): the same protocol as the in-memory
:class:`~engine.volume.MemoryTileStore`, writes included, and the same contract tests
(``tests/test_tile_store_contract.py``). An engine :class:`~engine.fusion.Volume` can fuse
into it directly; a persistent :class:`~storage.scene.Scene` reads its tiles through it and
writes them through units of work and checkpoints instead (``docs/storage.md``).

A write is durable when it returns: the chunks are written (each replaced atomically) and
fsynced before the owners are committed in one transaction.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from rangefuse.engine.grid import pack_keys, unique_keys, unpack_keys

from .catalog import Catalog
from .zarr_tiles import TileArrayError, ZarrTiles

__all__ = ["ZarrTileStore"]


class ZarrTileStore:
    """Tiles of the scene ``scene_id``: data in ``tiles``, owners in ``catalog``."""

    def __init__(self, tiles: ZarrTiles, catalog: Catalog, scene_id: str) -> None:
        self.tiles = tiles
        self.catalog = catalog
        self.scene_id = scene_id
        self.tile_size = tiles.tile_size

    def keys(self) -> np.ndarray:
        return unpack_keys(self.catalog.tile_keys(self.scene_id))

    def read(self, keys: np.ndarray) -> np.ndarray:
        return self.tiles.read(np.asarray(keys, np.int64).reshape(-1, 3))

    def owners(self, keys: np.ndarray) -> list[frozenset[str]]:
        packed = pack_keys(np.asarray(keys, np.int64).reshape(-1, 3))
        info = self.catalog.tile_scans(self.scene_id, packed)
        return [frozenset(s for s, own in info[p] if own) for p in packed.tolist()]

    def write(
        self,
        keys: np.ndarray,
        data: np.ndarray,
        owners: Sequence[frozenset[str]],
        *,
        take: bool = False,
    ) -> None:
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        T = self.tile_size
        if not isinstance(data, np.ndarray) or data.dtype != np.int64:
            raise TileArrayError(f"tile data must be int64 ({len(keys)}, {T}, {T}, {T})")
        if data.shape != (len(keys), T, T, T):
            raise TileArrayError(f"tile data must be int64 ({len(keys)}, {T}, {T}, {T})")
        if len(owners) != len(keys):
            raise TileArrayError(f"{len(owners)} owner sets for {len(keys)} tiles")
        for key, own in zip(keys.tolist(), owners, strict=True):
            if not own:
                raise TileArrayError(f"tile {tuple(key)} needs at least one owner")
        # a key given twice keeps its last tile, as separate writes would
        packed = pack_keys(keys)
        last = np.unique(packed[::-1], return_index=True)[1]
        rows = np.sort(len(packed) - 1 - last)
        self.tiles.write(keys[rows], data[rows])
        self.tiles.fsync(keys[rows])
        with self.catalog.transaction():
            self.catalog.set_tile_owners(
                self.scene_id, packed[rows], [owners[r] for r in rows.tolist()]
            )

    def delete(self, keys: np.ndarray) -> None:
        keys = unique_keys(np.asarray(keys, np.int64).reshape(-1, 3))
        if len(keys) == 0:
            return
        self.tiles.delete(keys)
        self.tiles.fsync(keys)
        with self.catalog.transaction():
            self.catalog.delete_tiles(self.scene_id, pack_keys(keys))
