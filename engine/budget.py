"""Resource budgets: how many tiles a scan will allocate, estimated before any work, and the
limits that refuse a scan, a batch of scans or a grid beyond them (``docs/budgets.md``).

:func:`estimate_scan` is cheap (NumPy on a subsample of the range map, no kernel, nothing
compiled; :mod:`engine._budget_estimate` for mapping mode): the service runs it in the
request that uploads a scan, the command line before it fuses anything. Closed mode: every
tile of the region of interest that the scan has in view, bounded by the region's tiles
inside the box of the scan's bounding sphere (:func:`engine.classify.bounding_sphere`);
:func:`grid_tiles` is the region's tile count.

The limits are declared once (:data:`LIMITS`); :class:`Limits` carries their values and,
for the messages, the name of what raises each (a setting, an option). Every refusal is a
:class:`BudgetError` that gives the estimate, the limit and that name.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ._budget_estimate import NO_KEYS, coarser, mapping_tiles
from .classify import bounding_sphere
from .errors import InvalidInputError
from .grid import KEY_LIMIT, GridSpec
from .scans import FusionParams, Scan

__all__ = [
    "LIMITS",
    "VOXEL_BYTES",
    "BudgetError",
    "Limit",
    "Limits",
    "ScanEstimate",
    "SceneTally",
    "check_grid",
    "check_scan",
    "check_scans",
    "check_scene",
    "estimate_scan",
    "grid_tiles",
]

#: Bytes of one voxel in memory (int64: fixed-point log-odds sum and count, DESIGN.md 2).
VOXEL_BYTES = 8


# --------------------------------------------------------------------------------------------
# the limits


@dataclass(frozen=True)
class Limit:
    """The declaration of one limit: name, default, what it counts (the settings and the
    command line's options derive from it)."""

    name: str
    default: int
    help: str
    unit: str  # "tiles" or "bytes"


#: Every limit, declared once (defaults and why: docs/budgets.md).
LIMITS: dict[str, Limit] = {
    lim.name: lim
    for lim in (
        Limit(
            "max_scan_tiles", 1_000_000,
            "most tiles one scan may allocate (estimated before it is accepted)", "tiles",
        ),
        Limit(
            "max_scene_tiles", 4_000_000,
            "most tiles a scene may hold (a closed grid: its region of interest)", "tiles",
        ),
        Limit(
            "max_scene_bytes", 64 * 2**30,
            "most voxel bytes a scene may hold (tiles x tile_size^3 x 8 bytes)", "bytes",
        ),
    )
}  # fmt: skip


@dataclass(frozen=True)
class Limits:
    """The limits a front end applies; ``knobs`` names, for the messages, what raises each
    (``RANGEFUSE_MAX_SCAN_TILES``, ``--max-scan-tiles``)."""

    max_scan_tiles: int = LIMITS["max_scan_tiles"].default
    max_scene_tiles: int = LIMITS["max_scene_tiles"].default
    max_scene_bytes: int = LIMITS["max_scene_bytes"].default
    knobs: Mapping[str, str] = field(default_factory=dict)

    def knob(self, name: str) -> str:
        return self.knobs.get(name, name)


class BudgetError(InvalidInputError):
    """A scan or a grid beyond a limit. ``limit`` names the limit (a key of :data:`LIMITS`
    or ``"key_range"``); ``estimate`` and ``allowed`` are the numbers compared."""

    def __init__(self, part: str, problem: str, limit: str, estimate: int, allowed: int) -> None:
        super().__init__(part, problem)
        self.limit = limit
        self.estimate = estimate
        self.allowed = allowed


# --------------------------------------------------------------------------------------------
# checks


def _size(n_bytes: int) -> str:
    """``542 GiB``, ``16 MiB``, ``3.5 KiB``, ``318,400 GiB``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n_bytes >= scale:
            digits = ",.3g" if n_bytes < 1000 * scale else ",.0f"
            return f"{n_bytes / scale:{digits}} {unit}"
    return f"{n_bytes} bytes"


def check_grid(grid: GridSpec, limits: Limits) -> None:
    """Refuse a closed grid whose region of interest holds more tiles or voxel bytes than a
    scene may (a closed scene may allocate every tile of it)."""
    if grid.mode != "closed":
        return
    tiles = grid_tiles(grid)
    n_bytes = tiles * grid.tile_size**3 * VOXEL_BYTES
    what = (
        f"the closed grid's region of interest holds {tiles:,} tiles of {grid.tile_size}^3 "
        f"voxels ({_size(n_bytes)}) at voxel size {grid.voxel_size:g} m"
    )
    if tiles > limits.max_scene_tiles:
        raise BudgetError(
            "bounds",
            f"{what}, over the limit of {limits.max_scene_tiles:,} tiles per scene "
            f"({limits.knob('max_scene_tiles')}); a larger voxel size or a smaller region fits",
            "max_scene_tiles", tiles, limits.max_scene_tiles,
        )  # fmt: skip
    if n_bytes > limits.max_scene_bytes:
        raise BudgetError(
            "bounds",
            f"{what}, over the limit of {_size(limits.max_scene_bytes)} per scene "
            f"({limits.knob('max_scene_bytes')}); a larger voxel size or a smaller region fits",
            "max_scene_bytes", n_bytes, limits.max_scene_bytes,
        )  # fmt: skip


class SceneTally:
    """The tiles a scene will hold once it has fused the scans whose estimates are added:
    the tiles it holds now plus the new scans' estimates, less their overlap; at most the
    region of interest's tiles in closed mode. The overlap is the share of distinct cells
    among the scans' sampled surface points, in cells coarse enough for the samples to be
    dense (:func:`engine._budget_estimate.coarser`)."""

    def __init__(self, grid: GridSpec, tiles_now: int = 0) -> None:
        self.grid = grid
        self.tiles_now = tiles_now
        self._added = 0
        self._keys: list[np.ndarray] = []
        self._level = 0

    def add(self, estimate: ScanEstimate) -> None:
        self._added += estimate.tiles
        if len(estimate.keys):
            self._keys.append(estimate.keys)
            self._level = max(self._level, estimate.level)

    @property
    def tiles(self) -> int:
        added = self._added
        if len(self._keys) > 1:
            cells = [coarser(k, self._level) for k in self._keys]
            distinct = len(np.unique(np.concatenate(cells)))
            added = math.ceil(added * distinct / sum(len(c) for c in cells))
        tiles = self.tiles_now + added
        if self.grid.mode == "closed":
            tiles = min(tiles, grid_tiles(self.grid))
        return tiles

    @property
    def bytes(self) -> int:
        return self.tiles * self.grid.tile_size**3 * VOXEL_BYTES


def check_scan(part: str, estimate: ScanEstimate, grid: GridSpec, limits: Limits) -> None:
    """Refuse a scan that would allocate more tiles than a scan may; ``part`` names it in
    the message (``scan``, ``scan room_0003``)."""
    if estimate.tiles <= limits.max_scan_tiles:
        return
    raise BudgetError(
        part,
        f"would allocate about {estimate.tiles:,} tiles of {grid.tile_size}^3 voxels "
        f"({_size(estimate.bytes)}) at voxel size {grid.voxel_size:g} m, over the limit of "
        f"{limits.max_scan_tiles:,} tiles per scan ({limits.knob('max_scan_tiles')}); "
        "a larger voxel size allocates fewer",
        "max_scan_tiles", estimate.tiles, limits.max_scan_tiles,
    )  # fmt: skip


def check_scene(tally: SceneTally, limits: Limits, part: str = "scene") -> None:
    """Refuse scans that would take the scene over its tiles or bytes."""
    tiles = tally.tiles
    now = f", about {tally.tiles_now:,} of them there already" if tally.tiles_now else ""
    if tiles > limits.max_scene_tiles:
        raise BudgetError(
            part,
            f"would hold about {tiles:,} tiles of {tally.grid.tile_size}^3 voxels{now}, over "
            f"the limit of {limits.max_scene_tiles:,} tiles per scene "
            f"({limits.knob('max_scene_tiles')})",
            "max_scene_tiles", tiles, limits.max_scene_tiles,
        )  # fmt: skip
    n_bytes = tiles * tally.grid.tile_size**3 * VOXEL_BYTES
    if n_bytes > limits.max_scene_bytes:
        raise BudgetError(
            part,
            f"would hold about {_size(n_bytes)} of voxels ({tiles:,} tiles of "
            f"{tally.grid.tile_size}^3 voxels x {VOXEL_BYTES} bytes{now}), over the limit of "
            f"{_size(limits.max_scene_bytes)} per scene ({limits.knob('max_scene_bytes')})",
            "max_scene_bytes", n_bytes, limits.max_scene_bytes,
        )  # fmt: skip


def check_scans(
    scans: Iterable[tuple[str, Scan]],
    params: FusionParams,
    grid: GridSpec,
    limits: Limits,
    tiles_now: int = 0,
) -> SceneTally:
    """Estimate every scan and refuse the first beyond ``limits.max_scan_tiles``, then the
    batch if the scene would pass its tiles or bytes (``tiles_now``: what it holds now).
    Messages name the scan (``scan NAME: ...``)."""
    tally = SceneTally(grid, tiles_now)
    for name, scan in scans:
        part = f"scan {name}"
        try:
            estimate = estimate_scan(scan, params, grid, with_keys=True)
        except BudgetError as exc:
            raise BudgetError(part, exc.problem, exc.limit, exc.estimate, exc.allowed) from None
        check_scan(part, estimate, grid, limits)
        tally.add(estimate)
    check_scene(tally, limits)
    return tally


# --------------------------------------------------------------------------------------------
# estimates


@dataclass(frozen=True)
class ScanEstimate:
    """What a scan will allocate, estimated (see the module's note).

    ``tiles`` is the estimate; ``keys`` the sorted distinct keys (packed as by
    :func:`engine.grid.pack_keys`) of the tiles of sampled surface points, and ``level``
    the cells (``2^level`` tiles a side) at which they lie densely: what
    :class:`SceneTally` needs to estimate how much scans overlap.
    """

    tiles: int
    tile_size: int
    keys: np.ndarray = field(repr=False)
    level: int = 0

    @property
    def voxels(self) -> int:
        return self.tiles * self.tile_size**3

    @property
    def bytes(self) -> int:
        return self.voxels * VOXEL_BYTES


def grid_tiles(grid: GridSpec) -> int:
    """Tiles of the region of interest (0 without one): what a closed grid may allocate."""
    if grid.bounds is None:
        return 0
    lo, hi = grid.roi_tiles()
    return math.prod(int(n) for n in np.maximum(hi - lo, 0))


def estimate_scan(
    scan: Scan, params: FusionParams, grid: GridSpec, with_keys: bool = False
) -> ScanEstimate:
    """Estimate the tiles :func:`engine.allocation.tiles_touched` allocates for ``scan``.

    NumPy only, on a subsample of the range map (:mod:`engine._budget_estimate`). Mapping
    mode: meant not to fall short of the real count by more than a small factor
    (``tests/test_budgets.py`` compares them on the synthetic scenes); closed mode: an upper
    bound. ``with_keys`` also samples the surface densely enough to put a point in most tiles
    it crosses (at most every pixel), for :class:`SceneTally`'s estimate of the overlap
    between scans.

    Raises
    ------
    BudgetError
        When the scan's band reaches beyond the tile keys' range (``limit="key_range"``).
    """
    if grid.mode == "closed":
        return ScanEstimate(_closed_tiles(scan, params, grid), grid.tile_size, NO_KEYS)
    tiles, keys, level, reach_m = mapping_tiles(scan, params, grid, with_keys)
    tile_m = grid.tile_size_m
    if not reach_m / tile_m < KEY_LIMIT - 2:
        raise BudgetError(
            "scan",
            f"its surface band reaches {reach_m:.4g} m from the origin, beyond the range of "
            f"tile keys: at voxel size {grid.voxel_size:g} m and tile size {grid.tile_size} a "
            f"scene spans +-{(KEY_LIMIT - 1) * tile_m:.4g} m on each axis",
            "key_range", math.ceil(reach_m / tile_m), KEY_LIMIT - 1,
        )  # fmt: skip
    if grid.bounds is not None:
        tiles = min(tiles, grid_tiles(grid))
    return ScanEstimate(tiles, grid.tile_size, keys, level)


def _closed_tiles(scan: Scan, params: FusionParams, grid: GridSpec) -> int:
    lo, hi = grid.roi_tiles()
    origin, radius = bounding_sphere(scan, params)
    if radius <= 0.0:
        return 0
    if math.isfinite(radius):
        tile_m = grid.tile_size_m
        lo = np.maximum(lo, np.floor((origin - radius) / tile_m).astype(np.int64) - 1)
        hi = np.minimum(hi, np.floor((origin + radius) / tile_m).astype(np.int64) + 2)
    return math.prod(int(n) for n in np.maximum(hi - lo, 0))
