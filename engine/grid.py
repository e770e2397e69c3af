"""The global voxel lattice and its tiles (DESIGN.md invariant 1).

Voxel ``(i, j, k)`` (integers, possibly negative) is centred at
``((i, j, k) + 1/2) * voxel_size`` in world coordinates. Tile ``(a, b, c)``
holds voxels ``a * tile_size .. (a + 1) * tile_size - 1`` along x, and so on.
The region of interest (ROI), when given as bounds, is the set of voxels whose
centres lie inside the box.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from .errors import InvalidGridError
from .params import PARAMS, current_names

__all__ = ["MODES", "Bounds", "GridSpec", "pack_keys", "unique_keys", "unpack_keys"]

MODES = PARAMS["mode"].choices
#: Tile keys must lie within +-KEY_LIMIT of the origin (21 bits per axis in a packed key).
KEY_LIMIT = 1 << 20

Bounds = tuple[float, float, float, float, float, float]
"""A box ``(x0, y0, z0, x1, y1, z1)`` in metres."""


@dataclass(frozen=True)
class GridSpec:
    """Voxel size, tile size, mode and region of interest of a scene.

    Parameters
    ----------
    voxel_size : float
        Edge of a voxel, metres.
    tile_size : int
        Voxels along each edge of a cubic tile.
    mode : {"mapping", "closed"}
        ``"mapping"`` allocates tiles around observed surfaces; ``"closed"`` allocates every
        tile of the region of interest that a line of sight crosses (needs ``bounds``).
    bounds : (x0, y0, z0, x1, y1, z1) or None
        Region of interest, world metres.
    """

    voxel_size: float
    tile_size: int = PARAMS["tile_size"].default
    mode: str = PARAMS["mode"].default
    bounds: Bounds | None = None

    def __post_init__(self) -> None:
        # each field as declared in engine/params.py; then the rules that join fields
        for field in ("voxel_size", "tile_size", "mode", "bounds"):
            value = PARAMS[field].validate(getattr(self, field), InvalidGridError)
            object.__setattr__(self, field, value)
        if self.bounds is not None:
            values = self.bounds
            for axis in range(3):
                if values[axis] >= values[axis + 3]:
                    name = "xyz"[axis]
                    raise InvalidGridError(
                        "bounds",
                        f"{name}0 must be less than {name}1, got {values[axis]} and "
                        f"{values[axis + 3]}",
                    )
            self._check_key_range(values)
            lo, hi = self.roi_voxels()
            if np.any(hi <= lo):
                raise InvalidGridError(
                    "bounds", f"the box holds no voxel centre at voxel size {self.voxel_size} m"
                )
        elif self.mode == "closed":
            raise InvalidGridError("bounds", "closed mode needs a region of interest")

    def _check_key_range(self, bounds: Bounds) -> None:
        """Refuse bounds with a voxel centre in a tile beyond the packed keys' range
        (``+-(KEY_LIMIT - 1)`` tiles; see :func:`pack_keys`): checked on the float values,
        before any of them becomes an integer."""
        limit_m = (KEY_LIMIT - 1) * self.tile_size_m
        for n, value in enumerate(bounds):
            if -limit_m < value < limit_m:
                continue
            name = "xyz"[n % 3] + "01"[n // 3]
            raise InvalidGridError(
                "bounds",
                f"{name} = {value:g} m lies beyond the range of tile keys: at voxel size "
                f"{self.voxel_size:g} m and tile size {self.tile_size} a scene spans "
                f"+-{limit_m:.6g} m on each axis ({KEY_LIMIT - 1:,} tiles from the origin)",
            )

    @property
    def tile_size_m(self) -> float:
        return self.tile_size * self.voxel_size

    def roi_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxel index range ``[lo, hi)`` (int64 (3,) each) of the region of interest."""
        if self.bounds is None:
            raise InvalidGridError("bounds", "this grid has no region of interest")
        b = np.asarray(self.bounds, np.float64)
        h = self.voxel_size
        lo = np.ceil(b[:3] / h - 0.5).astype(np.int64)
        hi = np.floor(b[3:] / h - 0.5).astype(np.int64) + 1
        return lo, hi

    def roi_tiles(self) -> tuple[np.ndarray, np.ndarray]:
        """Tile index range ``[lo, hi)`` of the tiles that hold voxels of the region of interest."""
        lo, hi = self.roi_voxels()
        t = self.tile_size
        return np.floor_divide(lo, t), np.floor_divide(hi - 1, t) + 1

    def to_dict(self) -> dict[str, Any]:
        return {
            "voxel_size": self.voxel_size,
            "tile_size": self.tile_size,
            "mode": self.mode,
            "bounds": None if self.bounds is None else list(self.bounds),
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> GridSpec:
        data = current_names(data)
        bounds = data.get("bounds")
        return GridSpec(
            voxel_size=data["voxel_size"],
            tile_size=data.get("tile_size", PARAMS["tile_size"].default),
            mode=data.get("mode", PARAMS["mode"].default),
            bounds=None if bounds is None else tuple(bounds),
        )


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """One int64 per tile key, ordered like the keys in lexicographic order.

    Keys must lie within ``+-KEY_LIMIT`` tiles of the origin (thousands of kilometres at
    millimetre voxels).
    """
    packed, inside = _pack(np.ascontiguousarray(keys, np.int64).reshape(-1, 3), KEY_LIMIT)
    if not inside:
        raise InvalidGridError(
            "bounds", f"the scene extends beyond {KEY_LIMIT} tiles from the origin"
        )
    return packed


def unpack_keys(packed: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_keys`: int64 (n, 3)."""
    return _unpack(np.ascontiguousarray(packed, np.int64).reshape(-1), KEY_LIMIT)


def unique_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted unique tile keys (int64 (n, 3)). Kernels throughout: the same steps in NumPy
    calls (``np.unique`` of the packed keys) cost about 0.2 ms per scan's allocation."""
    return unpack_keys(_sorted_unique(pack_keys(keys)))


@njit(cache=True)
def _pack(keys, limit):
    # 21 bits per axis, shifted by ``limit``; and whether every key is within it
    packed = np.empty(keys.shape[0], np.int64)
    inside = True
    for m in range(keys.shape[0]):
        a = keys[m, 0] + limit
        b = keys[m, 1] + limit
        c = keys[m, 2] + limit
        inside &= (a > 0) & (a < 2 * limit) & (b > 0) & (b < 2 * limit)
        inside &= (c > 0) & (c < 2 * limit)
        packed[m] = (a << 42) | (b << 21) | c
    return packed, inside


@njit(cache=True)
def _unpack(packed, limit):
    mask = (1 << 21) - 1
    out = np.empty((packed.shape[0], 3), np.int64)
    for m in range(packed.shape[0]):
        out[m, 0] = ((packed[m] >> 42) & mask) - limit
        out[m, 1] = ((packed[m] >> 21) & mask) - limit
        out[m, 2] = (packed[m] & mask) - limit
    return out


@njit(cache=True)
def _sorted_unique(values):
    out = np.sort(values)
    n = 0
    for m in range(out.shape[0]):
        if m == 0 or out[m] != out[n - 1]:
            out[n] = out[m]
            n += 1
    return out[:n].copy()
