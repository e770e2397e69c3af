"""Spatial indexes for the planner: existing tiles by position, scans by sensor position
(``docs/lidar.md``).

A long drive maps kilometres with a sensor that reaches tens of metres: a scan must find the
tiles it can reach, and a new tile the earlier scans that can reach it, without a pass over
the whole map.

* :class:`TileIndex` buckets sorted tile keys into cubic blocks of ``2**shift`` tiles; a
  query visits the blocks of a box of tiles (or, for a box wider than the map, the occupied
  blocks) and returns rows of the keys.
* :class:`SphereIndex` buckets scans' bounding spheres (:class:`engine.planner.Sphere`'s
  fields) by the cell of their centre; a query visits the cells within the largest radius of
  a box.

Both answer exactly what the pass over everything answered (:func:`reaches`: the distance
from a sphere's centre to a tile's box, within the radius plus one tile), in the same order;
``tests/test_spatial.py`` compares them with the pass on random sets.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .grid import pack_keys

__all__ = ["SphereIndex", "TileIndex", "box_distance", "reaches", "shift_for"]

#: A query enumerates the blocks of its box while they are at most this many times the
#: occupied blocks; past that it filters the occupied blocks instead.
_ENUMERATE_FACTOR = 4


def box_distance(
    lo: np.ndarray, hi: np.ndarray, origin: Sequence[float] | np.ndarray
) -> np.ndarray:
    """Distance from ``origin`` to each box ``[lo, hi]`` (float64 (n, 3) or (3,))."""
    o = np.asarray(origin, np.float64)
    return np.sqrt(np.sum(np.maximum(np.maximum(lo - o, o - hi), 0.0) ** 2, axis=-1))


def reaches(radius_m: float, distance: np.ndarray, tile_m: float) -> np.ndarray:
    """A sphere's test against distances to boxes, with one tile of slack (``radius_m`` may
    be ``inf``: everything)."""
    if not math.isfinite(radius_m):
        return np.ones(np.shape(distance), np.bool_)
    return distance <= radius_m + tile_m


def shift_for(radius_m: float, tile_m: float) -> int:
    """The block shift of a :class:`TileIndex` for queries of about ``radius_m``: blocks
    about a quarter of the radius wide (a query then visits about 10 blocks per axis)."""
    if not math.isfinite(radius_m) or radius_m <= 0.0:
        return 4
    tiles = radius_m / tile_m / 4.0
    return int(min(10, max(0, math.floor(math.log2(max(tiles, 1.0))))))


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, e)`` over the pairs (int64)."""
    lengths = ends - starts
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offsets = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
    return offsets + np.arange(total, dtype=np.int64)


class TileIndex:
    """Rows of tile keys (int64 (n, 3)) bucketed by block of ``2**shift`` tiles per side.

    Built once per set of keys (a sort of n packed block keys); a query costs the blocks it
    visits and the tiles in them, not n.
    """

    def __init__(self, keys: np.ndarray, shift: int) -> None:
        self.keys = np.ascontiguousarray(keys, np.int64).reshape(-1, 3)
        self.shift = int(shift)
        blocks = self.keys >> self.shift  # floor division, also for negative keys
        packed = pack_keys(blocks)
        self._order = np.argsort(packed, kind="stable").astype(np.int64)
        packed = packed[self._order]
        first = np.r_[True, packed[1:] != packed[:-1]] if len(packed) else np.zeros(0, np.bool_)
        self._block_packed = packed[first]
        self._block_keys = blocks[self._order][first]
        starts = np.flatnonzero(first)
        self._starts = starts.astype(np.int64)
        self._ends = np.r_[starts[1:], len(packed)].astype(np.int64)

    def __len__(self) -> int:
        return len(self.keys)

    def rows_in_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Sorted rows of the keys ``k`` with ``lo <= k <= hi`` on every axis (tile units)."""
        lo = np.asarray(lo, np.int64)
        hi = np.asarray(hi, np.int64)
        if len(self.keys) == 0 or np.any(hi < lo):
            return np.zeros(0, np.int64)
        blo = lo >> self.shift
        bhi = hi >> self.shift
        span = bhi - blo + 1
        n_box = float(span[0]) * float(span[1]) * float(span[2])
        if n_box <= _ENUMERATE_FACTOR * len(self._block_packed):
            grid = np.meshgrid(*(np.arange(blo[a], bhi[a] + 1) for a in range(3)), indexing="ij")
            wanted = pack_keys(np.stack([g.reshape(-1) for g in grid], axis=1))
            at = np.searchsorted(self._block_packed, wanted)
            at_ok = at < len(self._block_packed)
            found = at[at_ok][self._block_packed[at[at_ok]] == wanted[at_ok]]
        else:
            bk = self._block_keys
            found = np.flatnonzero(np.all((bk >= blo) & (bk <= bhi), axis=1))
        rows = self._order[_ranges(self._starts[found], self._ends[found])]
        k = self.keys[rows]
        rows = rows[np.all((k >= lo) & (k <= hi), axis=1)]
        return np.sort(rows)

    def rows_near(self, origin: Sequence[float], radius_m: float, tile_m: float) -> np.ndarray:
        """Sorted rows of the tiles whose box a sphere reaches (:func:`reaches`): the rows
        where ``planner.tiles_near`` is True."""
        if not math.isfinite(radius_m):
            return np.arange(len(self.keys), dtype=np.int64)
        o = np.asarray(origin, np.float64)
        reach = radius_m + tile_m
        lo = np.floor((o - reach) / tile_m).astype(np.int64) - 1
        hi = np.floor((o + reach) / tile_m).astype(np.int64) + 1
        rows = self.rows_in_box(lo, hi)
        k_lo = self.keys[rows] * tile_m
        return rows[reaches(radius_m, box_distance(k_lo, k_lo + tile_m, o), tile_m)]


def _inside(cell: tuple[int, int, int], lo: tuple[int, int, int], hi: tuple[int, int, int]) -> bool:
    return all(a <= x <= b for a, x, b in zip(lo, cell, hi, strict=True))


class SphereIndex:
    """Bounding spheres (scan id, centre, radius) bucketed by the cell of their centre.

    Spheres can be added and removed one by one (a volume keeps one for its scans). A query
    for a box visits the cells within the largest radius held, so its cost is the spheres
    near the box, not all of them. Unbounded spheres (``inf`` radius) reach everything and are
    kept apart.
    """

    def __init__(self, cell_m: float = 16.0) -> None:
        if not (cell_m > 0.0 and math.isfinite(cell_m)):
            raise ValueError(f"cell_m must be a positive length, got {cell_m}")
        self.cell_m = float(cell_m)
        self._cells: dict[tuple[int, int, int], dict[str, int]] = {}
        self._where: dict[str, tuple[tuple[int, int, int] | None, int]] = {}
        self._spheres: dict[str, tuple[tuple[float, float, float], float]] = {}
        self._unbounded: dict[str, int] = {}
        self._seq = 0
        self._max_radius = 0.0

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, scan_id: object) -> bool:
        return scan_id in self._where

    def add(self, scan_id: str, origin: Sequence[float], radius_m: float) -> None:
        """Add a sphere (a scan id given again replaces its sphere)."""
        if scan_id in self._where:
            self.remove(scan_id)
        centre = (float(origin[0]), float(origin[1]), float(origin[2]))
        self._seq += 1
        self._spheres[scan_id] = (centre, float(radius_m))
        if not math.isfinite(radius_m):
            self._unbounded[scan_id] = self._seq
            self._where[scan_id] = (None, self._seq)
            return
        cell = self._cell(centre)
        self._cells.setdefault(cell, {})[scan_id] = self._seq
        self._where[scan_id] = (cell, self._seq)
        self._max_radius = max(self._max_radius, float(radius_m))

    def sphere(self, scan_id: str) -> tuple[tuple[float, float, float], float]:
        """The centre and radius of a sphere held (KeyError for another id)."""
        return self._spheres[scan_id]

    def remove(self, scan_id: str) -> None:
        """Forget a sphere (missing ids are ignored)."""
        where = self._where.pop(scan_id, None)
        if where is None:
            return
        self._spheres.pop(scan_id)
        cell, _ = where
        if cell is None:
            self._unbounded.pop(scan_id, None)
            return
        members = self._cells[cell]
        members.pop(scan_id, None)
        if not members:
            del self._cells[cell]

    def _cell(self, p: Sequence[float] | np.ndarray) -> tuple[int, int, int]:
        c = self.cell_m
        return (math.floor(p[0] / c), math.floor(p[1] / c), math.floor(p[2] / c))

    def near_box(self, lo_m: np.ndarray, hi_m: np.ndarray, tile_m: float) -> list[str]:
        """Ids of the spheres that reach the box ``[lo_m, hi_m]`` (metres) within one tile
        of slack (:func:`reaches`), in the order they were added."""
        lo_m = np.asarray(lo_m, np.float64)
        hi_m = np.asarray(hi_m, np.float64)
        found: dict[str, int] = dict(self._unbounded)
        if self._cells:
            pad = self._max_radius + tile_m
            clo = self._cell(lo_m - pad)
            chi = self._cell(hi_m + pad)
            n_box = math.prod(b - a + 1 for a, b in zip(clo, chi, strict=True))
            if n_box <= _ENUMERATE_FACTOR * len(self._cells):
                cells = (
                    (i, j, k)
                    for i in range(clo[0], chi[0] + 1)
                    for j in range(clo[1], chi[1] + 1)
                    for k in range(clo[2], chi[2] + 1)
                )
            else:
                cells = (c for c in self._cells if _inside(c, clo, chi))
            for cell in cells:
                members = self._cells.get(cell)
                if not members:
                    continue
                for scan_id, seq in members.items():
                    centre, radius = self._spheres[scan_id]
                    if reaches(radius, box_distance(lo_m, hi_m, centre), tile_m):
                        found[scan_id] = seq
        return sorted(found, key=found.__getitem__)
