"""Where tiles live: a small store protocol, its in-memory implementation, dense export.

A tile is an int64 array ``(T, T, T)`` of packed voxels (see
:mod:`engine.certainty`: fixed-point sum of log-odds and count of informing
scans; 0 is *unknown*) plus the set of scan ids that *own* it, i.e. whose
allocation (:func:`engine.allocation.tiles_touched`) includes it. A tile exists
exactly while it has an owner. The Zarr store of :mod:`storage` implements the
same protocol; both pass the same conformance tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np

from ._memory import zeros
from .certainty import decode_logodds
from .errors import InvalidGridError
from .grid import Bounds, GridSpec

__all__ = ["DenseGrid", "MemoryTileStore", "TileReader", "TileStore", "dense_logodds", "key_tuple"]

#: Refuse to build dense grids above this many voxels (4 GB of float32).
MAX_DENSE_VOXELS = 1 << 30
#: Most bytes of spare room one growth of :class:`MemoryTileStore`'s pool reserves.
POOL_BLOCK_BYTES = 64 << 20


def key_tuple(key: np.ndarray | Sequence[int]) -> tuple[int, int, int]:
    return int(key[0]), int(key[1]), int(key[2])


def _tuples(keys: np.ndarray) -> list[tuple[int, int, int]]:
    """Rows of int64 (n, 3) keys as tuples of Python ints (one conversion for all)."""
    return [(a, b, c) for a, b, c in np.asarray(keys, np.int64).reshape(-1, 3).tolist()]


class TileReader(Protocol):
    """Tiles to read (meshing, dense export): packed voxel data by integer tile key."""

    tile_size: int

    def keys(self) -> np.ndarray:
        """All tile keys, int64 (n, 3), sorted."""
        ...

    def read(self, keys: np.ndarray) -> np.ndarray:
        """Voxel data of ``keys`` as int64 (n, T, T, T); a missing tile reads as unknown (0)."""
        ...


class TileStore(TileReader, Protocol):
    """Storage of tiles: packed voxel data and owners, by integer tile key."""

    def owners(self, keys: np.ndarray) -> list[frozenset[str]]:
        """Owner scan ids of each tile (empty for a missing tile)."""
        ...

    def write(
        self,
        keys: np.ndarray,
        data: np.ndarray,
        owners: Sequence[frozenset[str]],
        *,
        take: bool = False,
    ) -> None:
        """Create or replace tiles (each must have at least one owner). With ``take`` the
        caller hands ``data`` over (it will neither read nor write it again): a store may keep
        the array itself instead of a copy."""
        ...

    def delete(self, keys: np.ndarray) -> None:
        """Remove tiles; missing ones are ignored."""
        ...


class MemoryTileStore:
    """Tiles in memory: the in-memory twin of the Zarr store.

    Voxel data live in a pool of tiles indexed by a dict from key to slot; freed slots are
    reused. The pool is a list of blocks (arrays of tiles): it grows by a block as large as
    the write that needs it or as the pool up to :data:`POOL_BLOCK_BYTES`, whichever is
    larger, never by copying the tiles it holds (doubling one array copied the whole map and
    held the old array and the new at once: 2.6 GB at 40 k tiles of 16^3 on a 2.5 km drive
    at 10 cm, docs/lidar.md). It shrinks to one block of twice its tiles when three quarters
    of it are free. A write is one copy into the pool per block it touches: a 1 cm room batch
    used to make 6,185 separate 32 KB copies, 1.3 ms per frame.
    """

    def __init__(self, tile_size: int, *, block_tiles: int | None = None) -> None:
        self.tile_size = int(tile_size)
        T = self.tile_size
        #: most tiles in a block the pool grows by (``block_tiles`` is for tests)
        most = POOL_BLOCK_BYTES // (8 * T**3) if block_tiles is None else block_tiles
        self._block_tiles = max(1, int(most))
        self._slot: dict[tuple[int, int, int], int] = {}
        self._owners: dict[tuple[int, int, int], frozenset[str]] = {}
        self._blocks: list[np.ndarray] = []  # each (n, T, T, T) int64; slots run through them
        self._free: list[int] = []  # the pool's unused slots, taken from the end

    def __len__(self) -> int:
        return len(self._slot)

    def keys(self) -> np.ndarray:
        if not self._slot:
            return np.zeros((0, 3), np.int64)
        return np.array(sorted(self._slot), dtype=np.int64).reshape(-1, 3)

    def _slots(self, keys: np.ndarray) -> np.ndarray:
        """Slot of each key, -1 where the tile is missing."""
        return np.array([self._slot.get(key, -1) for key in _tuples(keys)], np.int64)

    def _starts(self) -> np.ndarray:
        """The first slot of each block, then the pool's capacity."""
        return np.cumsum([0, *(len(block) for block in self._blocks)], dtype=np.int64)

    def _by_block(
        self, slots: np.ndarray
    ) -> list[tuple[np.ndarray, np.ndarray | slice, np.ndarray]]:
        """For each block that holds some of ``slots`` (all valid): the block, the
        positions in ``slots`` it holds (a slice when one block holds them all, so that
        indexing with it copies nothing) and their rows in it."""
        if len(self._blocks) == 1:
            return [(self._blocks[0], slice(0, len(slots)), slots)]
        starts = self._starts()
        block = np.searchsorted(starts, slots, side="right") - 1
        out: list[tuple[np.ndarray, np.ndarray | slice, np.ndarray]] = []
        for b in np.unique(block).tolist():
            at = np.flatnonzero(block == b)
            out.append((self._blocks[b], at, slots[at] - starts[b]))
        return out

    def read(self, keys: np.ndarray) -> np.ndarray:
        T = self.tile_size
        slots = self._slots(keys)
        found = np.flatnonzero(slots >= 0)
        parts = self._by_block(slots[found])
        if len(found) == len(slots) and len(parts) == 1:
            block, _, rows = parts[0]
            return block[rows]  # one gather
        if len(found) == len(slots):  # filled whole: numpy's memory, as a gather's own
            out = np.empty((len(slots), T, T, T), np.int64)
        else:
            out = zeros((len(slots), T, T, T), np.int64)
        for block, at, rows in parts:
            out[found[at]] = block[rows]
        return out

    def owners(self, keys: np.ndarray) -> list[frozenset[str]]:
        return [self._owners.get(key, frozenset()) for key in _tuples(keys)]

    def write(
        self,
        keys: np.ndarray,
        data: np.ndarray,
        owners: Sequence[frozenset[str]],
        *,
        take: bool = False,
    ) -> None:
        T = self.tile_size
        if data.shape != (len(keys), T, T, T) or data.dtype != np.int64:
            raise ValueError(f"tile data must be int64 ({len(keys)}, {T}, {T}, {T})")
        tuples = _tuples(keys)
        if len(owners) != len(tuples):
            raise ValueError(f"{len(owners)} owner sets for {len(tuples)} tiles")
        for key, own in zip(tuples, owners, strict=True):
            if not own:
                raise ValueError(f"tile {key} needs at least one owner")
        # a key given twice keeps its last tile, as separate writes would
        last = {key: n for n, key in enumerate(tuples)}
        if take and not self._slot and len(last) == len(tuples) and data.flags.c_contiguous:
            # the first write to an empty store (a batch's fresh tiles): keep the array
            self._blocks = [data]
            self._slot = dict(zip(tuples, range(len(tuples)), strict=True))
            self._free = []
            self._owners = {key: frozenset(own) for key, own in zip(tuples, owners, strict=True)}
            return
        rows = np.fromiter(last.values(), np.int64, len(last))
        new = [key for key in last if key not in self._slot]
        self._reserve(len(new))
        for key in new:
            self._slot[key] = self._free.pop()
        slots = np.array([self._slot[key] for key in last], np.int64)
        source = data if len(rows) == len(tuples) else data[rows]
        for block, at, rows_in_block in self._by_block(slots):
            block[rows_in_block] = source[at]
        for key, n in last.items():
            self._owners[key] = frozenset(owners[n])

    def _reserve(self, more: int) -> None:
        """Make room for ``more`` new tiles in the free list: a new block, as large as
        ``more`` needs or as the pool up to a block's most, whichever is larger."""
        if more <= len(self._free):
            return
        used = int(self._starts()[-1])
        size = max(more - len(self._free), min(max(used, 64), self._block_tiles))
        T = self.tile_size
        self._blocks.append(zeros((size, T, T, T), np.int64))
        self._free = list(range(used + size - 1, used - 1, -1)) + self._free

    def delete(self, keys: np.ndarray) -> None:
        for key in _tuples(keys):
            slot = self._slot.pop(key, None)
            if slot is not None:
                self._free.append(slot)
            self._owners.pop(key, None)
        capacity = int(self._starts()[-1])
        if capacity > 64 and 4 * len(self._slot) < capacity:
            self._compact()

    def _compact(self) -> None:
        """Move the tiles to one block of twice their number (after many deletions)."""
        live = list(self._slot)
        size = max(2 * len(live), 64)
        T = self.tile_size
        pool = zeros((size, T, T, T), np.int64)
        for block, at, rows in self._by_block(np.array([self._slot[k] for k in live], np.int64)):
            pool[at] = block[rows]
        self._blocks = [pool]
        self._slot = {key: n for n, key in enumerate(live)}
        self._free = list(range(size - 1, len(live) - 1, -1))


@dataclass(frozen=True, eq=False)
class DenseGrid:
    """A dense block of the fused volume (FORMAT.md ``--grid-out``).

    ``logodds[i, j, k]`` (float32, NaN = unknown) is the voxel centred at
    ``origin + (i, j, k) * voxel_size``; ``first_voxel`` is its global voxel index.
    """

    logodds: np.ndarray
    origin: np.ndarray
    voxel_size: float
    first_voxel: np.ndarray


def dense_logodds(
    store: TileReader, grid: GridSpec, bounds: Sequence[float] | None = None
) -> DenseGrid:
    """Decode the tiles into a dense grid.

    The grid covers the voxels whose centres lie in ``bounds``, else in the grid's region of
    interest, else the bounding box of all tiles. Voxels in no tile are unknown (NaN).
    """
    T = store.tile_size
    keys = store.keys()
    if bounds is not None:
        box = cast("Bounds", tuple(bounds))  # GridSpec checks it
        lo, hi = GridSpec(grid.voxel_size, T, "mapping", box).roi_voxels()
    elif grid.bounds is not None:
        lo, hi = grid.roi_voxels()
    elif len(keys):
        lo = keys.min(axis=0) * T
        hi = (keys.max(axis=0) + 1) * T
    else:
        lo = np.zeros(3, np.int64)
        hi = np.zeros(3, np.int64)
    shape = tuple(int(x) for x in hi - lo)
    n_voxels = int(np.prod(shape, dtype=np.int64))
    if n_voxels > MAX_DENSE_VOXELS:
        raise InvalidGridError(
            "bounds",
            f"a dense grid of {shape[0]} x {shape[1]} x {shape[2]} voxels "
            f"({4 * n_voxels / 2**30:.1f} GiB) is too large; give smaller bounds",
        )
    out = np.full(shape, np.nan, np.float32)
    if len(keys):
        first = keys * T
        inside = np.all((first < hi) & (first + T > lo), axis=1)
        for key, tile in zip(keys[inside], store.read(keys[inside]), strict=True):
            a0 = key * T
            src_lo = np.maximum(lo - a0, 0)
            src_hi = np.minimum(hi - a0, T)
            dst_lo = a0 + src_lo - lo
            dst_hi = a0 + src_hi - lo
            out[dst_lo[0] : dst_hi[0], dst_lo[1] : dst_hi[1], dst_lo[2] : dst_hi[2]] = (
                decode_logodds(
                    tile[src_lo[0] : src_hi[0], src_lo[1] : src_hi[1], src_lo[2] : src_hi[2]]
                )
            )
    h = grid.voxel_size
    return DenseGrid(
        logodds=out,
        origin=(lo.astype(np.float64) + 0.5) * h,
        voxel_size=h,
        first_voxel=lo.astype(np.int64),
    )
