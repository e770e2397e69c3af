"""The planner: which tiles a change to the volume writes, and which scan goes into which tile
(DESIGN.md invariants 1 and 4; ``docs/planner.md``).

These rules make the volume exact, the same bits whatever the order in which scans arrive
and however the work is split. They are written here once: the in-memory
:class:`~engine.fusion.Volume` and the persistent scene of :mod:`storage` both carry out
the plans made here and decide none of this themselves.

1. **Allocation.** A new scan allocates :func:`~engine.allocation.tiles_touched`; the tiles
   among them that do not exist yet are *created* (they start from unknown).
2. **A new scan reaches every tile it sees.** It is added to every tile, existing or
   created, that it has in view (free space seen through old tiles included).
3. **Backfill.** A created tile also receives every earlier scan that has it in view. The
   earlier scans tested are those whose bounding sphere (:class:`Sphere`) meets the box of
   the created tiles (a conservative test: the others see none of them).
4. **Owners.** A new scan owns the tiles it allocates; a tile exists while it has an owner.
5. **Removal.** Removing a scan subtracts it from every tile it has in view that keeps
   another owner, deletes the tiles it alone owned, and drops its ownership everywhere.
6. **Rebuild.** A tile rebuilt from the scans starts from unknown and receives every scan
   that has it in view: a backfill of tiles treated as created.

"In view" is :func:`~engine.classify.classify_tiles` with the plan's ``halo``: 0 tests a
tile's voxel centres (what fusion needs), 1 adds the one-voxel halo above them (the cube
edges of the tile's mesh: an executor that keeps tile meshes up to date plans with 1, so
that the tiles a scan writes are also the tiles whose meshes it may change). The extra
tiles of a halo receive nothing from the kernel: both give the same bits.

A plan is made in two stages, so that an executor can interleave them with its work:
:func:`plan_add` (and the others) decide the tiles and the steps at once, and
:meth:`Plan.views` classifies each step's scan against its candidate tiles when the
executor asks for it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from ._memory import Scratch
from .allocation import tiles_touched
from .classify import FREE, OUT, classify_tiles, reach_radius
from .grid import KEY_LIMIT, GridSpec, pack_keys, unique_keys, unpack_keys
from .scans import PreparedScan
from .spatial import SphereIndex, TileIndex, box_distance, reaches, shift_for

__all__ = [
    "Plan",
    "Sphere",
    "Step",
    "View",
    "plan_add",
    "plan_rebuild",
    "plan_remove",
    "scans_near",
    "tiles_near",
]

#: Loads a scan prepared for the kernels, by id.
Loader = Callable[[str], PreparedScan]

_NO_KEYS = np.zeros((0, 3), np.int64)
_NO_ROWS = np.zeros(0, np.int64)


@dataclass(frozen=True)
class Sphere:
    """A ball around a scan's sensor outside which the scan informs nothing.

    ``radius_m`` may be ``inf`` (a sensor whose reach is unbounded).
    """

    scan_id: str
    origin: tuple[float, float, float]
    radius_m: float


@dataclass(frozen=True)
class Step:
    """One scan's part of a plan: add (``sign`` 1) or subtract (-1) the scan in the tiles
    ``candidates`` (rows of :attr:`Plan.keys`) that it has in view."""

    scan_id: str
    candidates: np.ndarray
    sign: int = 1


@dataclass(frozen=True)
class View:
    """Step number ``step`` of a plan, classified: the rows of :attr:`Plan.keys` the scan
    has in view, and for each whether the scan sees it as free space throughout (it then
    adds ``logit(rho)`` to every voxel). ``bounds`` are the scan's per-quad bounds when
    classifying computed them (in the scratch of :meth:`Plan.views`: valid until the next
    view is drawn), else None."""

    scan_id: str
    step: int
    rows: np.ndarray
    free: np.ndarray
    sign: int
    bounds: np.ndarray | None = None


@dataclass
class Plan:
    """What a change writes.

    Attributes
    ----------
    keys : int64 (n, 3)
        Sorted tile keys: every tile a step may write, and the created ones.
    created : bool (n,)
        Tiles that start from unknown instead of their stored data (created, or rebuilt).
    steps : list of Step
        The scans to add or subtract, in order: the new scans first.
    owned : dict
        Rows of ``keys`` each new scan owns (rule 4).
    disowned : str or None
        The scan whose ownership goes everywhere (a removal).
    deleted : int64 (m, 3)
        Tiles that go away (a removal: the tiles the scan alone owned).
    halo : int
        The halo of "in view" (see the module's note).
    """

    grid: GridSpec
    keys: np.ndarray
    created: np.ndarray
    steps: list[Step]
    halo: int = 0
    owned: dict[str, np.ndarray] = field(default_factory=dict)
    disowned: str | None = None
    deleted: np.ndarray = field(default_factory=lambda: _NO_KEYS)

    def views(self, load: Loader, scratch: Scratch | None = None) -> Iterator[View]:
        """Each step classified, in order (see :class:`View`); steps whose scan sees none
        of its candidates are skipped. ``load`` gives a step's scan."""
        for n, step in enumerate(self.steps):
            if len(step.candidates) == 0:
                continue
            scan = load(step.scan_id)
            bounds = None
            if not scan.has_pyramid:  # the bounds once, for the pyramid and the kernel
                bounds = scan.quad_bounds(scratch)
            status = classify_tiles(scan, self.grid, self.keys[step.candidates], self.halo)
            seen = status != OUT
            if seen.any():
                yield View(step.scan_id, n, step.candidates[seen], status[seen] == FREE,
                           step.sign, bounds)  # fmt: skip

    def created_keys(self) -> np.ndarray:
        return self.keys[self.created]

    def owned_rows(self) -> np.ndarray:
        """Rows that new scans own (sorted, unique)."""
        return np.unique(np.concatenate([_NO_ROWS, *self.owned.values()]))

    def owners_after(
        self, rows: np.ndarray, before: Sequence[frozenset[str]]
    ) -> list[frozenset[str]]:
        """The owners of the tiles ``rows`` once the plan is carried out, from ``before``
        (rule 4: the new scans join the owners of the tiles they allocate; a removal drops
        its scan)."""
        ids = list(self.owned)
        pair_rows = np.concatenate([_NO_ROWS, *(self.owned[s] for s in ids)])
        pair_scans = np.repeat(np.arange(len(ids)), [len(self.owned[s]) for s in ids])
        order = np.argsort(pair_rows, kind="stable")
        pair_rows, pair_scans = pair_rows[order], pair_scans[order]
        joining: dict[int, set[str]] = {}
        if len(pair_rows):
            starts = np.flatnonzero(np.r_[True, pair_rows[1:] != pair_rows[:-1]])
            for row, group in zip(
                pair_rows[starts].tolist(), np.split(pair_scans, starts[1:]), strict=True
            ):
                joining[row] = {ids[k] for k in group.tolist()}
        gone = frozenset() if self.disowned is None else frozenset({self.disowned})
        return [
            (own | joining.get(row, set())) - gone
            for row, own in zip(np.asarray(rows).tolist(), before, strict=True)
        ]


def _reaches(sphere: Sphere, distance: np.ndarray, tile_m: float) -> np.ndarray:
    """The sphere's test (with one tile of slack) against distances to boxes."""
    return reaches(sphere.radius_m, distance, tile_m)


def scans_near(spheres: Iterable[Sphere], keys: np.ndarray, grid: GridSpec) -> list[str]:
    """Ids of the scans whose sphere meets the box of the tiles ``keys`` (rule 3's test;
    in the order given)."""
    if len(keys) == 0:
        return []
    tile_m = grid.tile_size_m
    lo = keys.min(axis=0) * tile_m
    hi = (keys.max(axis=0) + 1) * tile_m
    return [s.scan_id for s in spheres if _reaches(s, box_distance(lo, hi, s.origin), tile_m)]


def tiles_near(sphere: Sphere, keys: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Mask of the tiles ``keys`` (int64 (n, 3)) whose box the sphere meets."""
    tile_m = grid.tile_size_m
    lo = keys * tile_m
    return _reaches(sphere, box_distance(lo, lo + tile_m, sphere.origin), tile_m)


def _isin(keys: np.ndarray, among: np.ndarray) -> np.ndarray:
    if len(among) == 0:
        return np.zeros(len(keys), np.bool_)
    return np.isin(pack_keys(keys), pack_keys(among))


def _rows_of(keys: np.ndarray, subset: np.ndarray) -> np.ndarray:
    """Rows of sorted unique ``keys`` that hold each member of ``subset``."""
    return np.searchsorted(pack_keys(keys), pack_keys(subset))


def plan_add(
    grid: GridSpec,
    existing: np.ndarray,
    new: Sequence[str],
    earlier: Iterable[Sphere] | SphereIndex,
    load: Loader,
    *,
    halo: int = 0,
    scratch: Scratch | None = None,
    max_pairs: int | None = None,
) -> Plan:
    """Plan the fusion of the scans ``new`` into a volume whose tiles are ``existing``
    (int64 (n, 3), sorted) and whose earlier scans are bounded by ``earlier`` (spheres, or a
    :class:`~engine.spatial.SphereIndex` of them): rules 1 to 4.

    ``load`` gives a scan prepared for the kernels (the new ones are allocated here, one at
    a time; the earlier ones are only loaded when :meth:`Plan.views` reaches them).

    A new scan's candidates are the tiles its sphere reaches (:func:`tiles_near`, through a
    :class:`~engine.spatial.TileIndex`): it informs nothing farther, so the tiles beyond
    were out of its view. Its work is then what it can reach, not the whole map.

    With ``max_pairs``, the plan takes the longest prefix of ``new`` (one scan at least)
    whose (scan, tile) pairs stay within it (:class:`_PairCount`): what a plan, its views
    and the units made from them hold grows with these pairs. The scans taken are the keys
    of :attr:`Plan.owned`, in order; the caller plans the others next.
    """
    existing = np.asarray(existing, np.int64).reshape(-1, 3)
    if not isinstance(earlier, SphereIndex):
        earlier = list(earlier)
    budget = None if max_pairs is None else _PairCount(grid, existing, earlier, set(new), max_pairs)
    touched: dict[str, np.ndarray] = {}
    spheres: dict[str, Sphere] = {}
    for scan_id in new:
        scan = load(scan_id)
        tiles = tiles_touched(scan, grid, scratch)
        sphere = Sphere(scan_id, _origin(scan), reach_radius(scan))
        if budget is not None and not budget.take(sphere, tiles):
            break
        touched[scan_id], spheres[scan_id] = tiles, sphere
    new = list(touched)
    all_touched = unique_keys(np.concatenate([_NO_KEYS, *touched.values()]))
    created_keys = all_touched[~_isin(all_touched, existing)]
    keys = unique_keys(np.concatenate([existing, created_keys]))
    created = _isin(keys, created_keys)
    tile_m = grid.tile_size_m
    radii = [s.radius_m for s in spheres.values() if math.isfinite(s.radius_m)]
    index = TileIndex(keys, shift_for(max(radii, default=math.inf), tile_m))
    steps = [
        Step(scan_id, index.rows_near(spheres[scan_id].origin, spheres[scan_id].radius_m, tile_m))
        for scan_id in new
    ]
    if len(created_keys):
        exclude = set(new)
        backfill = np.flatnonzero(created)
        if isinstance(earlier, SphereIndex):
            lo = created_keys.min(axis=0) * tile_m
            hi = (created_keys.max(axis=0) + 1) * tile_m
            nearby = [s for s in earlier.near_box(lo, hi, tile_m) if s not in exclude]
        else:
            near = (s for s in earlier if s.scan_id not in exclude)
            nearby = scans_near(near, created_keys, grid)
        steps += [Step(scan_id, backfill) for scan_id in nearby]
    owned = {scan_id: _rows_of(keys, tiles) for scan_id, tiles in touched.items()}
    return Plan(grid, keys, created, steps, halo, owned)


class _PairCount:
    """The (scan, tile) pairs of a plan of the new scans taken so far, counted as they are
    taken: each scan's allocated tiles (its owned rows), its candidates (every tile, existing
    or created by any scan taken, that its sphere reaches) and, for every earlier scan whose
    sphere reaches created tiles, those tiles (a bound on its backfill view). Exact for the
    first two: a scan taken later adds its created tiles to the candidates of those before.
    """

    def __init__(
        self,
        grid: GridSpec,
        existing: np.ndarray,
        earlier: list[Sphere] | SphereIndex,
        new: set[str],
        most: int,
    ) -> None:
        self.grid = grid
        self.most = most
        self.existing = existing
        self.existing_packed = np.sort(pack_keys(existing))
        self.index: TileIndex | None = None
        self.created_packed = np.zeros(0, np.int64)  # sorted
        self.earlier = earlier
        self.new = new
        self.taken: list[Sphere] = []
        self.pairs = 0

    def take(self, sphere: Sphere, tiles: np.ndarray) -> bool:
        """Count the pairs ``sphere``'s scan (allocating ``tiles``) adds; take it unless
        it brings the count over ``most`` (the first scan is always taken)."""
        tile_m = self.grid.tile_size_m
        packed = np.unique(pack_keys(tiles))
        fresh = ~_sorted_isin(packed, self.existing_packed)
        fresh &= ~_sorted_isin(packed, self.created_packed)
        delta_packed = packed[fresh]
        delta = unpack_keys(delta_packed)
        at = np.searchsorted(self.created_packed, delta_packed)
        created_packed = np.insert(self.created_packed, at, delta_packed)
        if self.index is None:
            self.index = TileIndex(self.existing, shift_for(sphere.radius_m, tile_m))
        added = len(tiles)
        added += len(self.index.rows_near(sphere.origin, sphere.radius_m, tile_m))
        created = unpack_keys(_in_x_reach(created_packed, sphere, tile_m))
        added += int(tiles_near(sphere, created, self.grid).sum())
        if len(delta):
            taken = _reaching_box(self.taken, delta, tile_m)
            added += _pairs_near([*taken, *self._earlier_near(delta)], delta, self.grid)
        if self.taken and self.pairs + added > self.most:
            return False
        self.pairs += added
        self.taken.append(sphere)
        self.created_packed = created_packed
        return True

    def _earlier_near(self, keys: np.ndarray) -> list[Sphere]:
        """The earlier scans' spheres that reach the box of ``keys`` (new scans excluded)."""
        if isinstance(self.earlier, SphereIndex):
            tile_m = self.grid.tile_size_m
            lo = keys.min(axis=0) * tile_m
            hi = (keys.max(axis=0) + 1) * tile_m
            ids = [s for s in self.earlier.near_box(lo, hi, tile_m) if s not in self.new]
            return [Sphere(s, *self.earlier.sphere(s)) for s in ids]
        near = set(scans_near(self.earlier, keys, self.grid)) - self.new
        return [s for s in self.earlier if s.scan_id in near]


def _in_x_reach(packed: np.ndarray, sphere: Sphere, tile_m: float) -> np.ndarray:
    """The packed keys (sorted) whose x is within the sphere's reach and a tile more on each
    side (keys pack x first: one slice); all of them when the sphere is unbounded."""
    if not math.isfinite(sphere.radius_m):
        return packed
    reach = sphere.radius_m + tile_m
    x = [math.floor((sphere.origin[0] + d) / tile_m) + n for d, n in ((-reach, -1), (reach, 1))]
    x = [min(max(v, 1 - KEY_LIMIT), KEY_LIMIT - 1) for v in x]
    bounds = pack_keys(np.array([[x[0], 1 - KEY_LIMIT, 1 - KEY_LIMIT],
                                 [x[1], KEY_LIMIT - 1, KEY_LIMIT - 1]]))  # fmt: skip
    lo = int(np.searchsorted(packed, bounds[0], side="left"))
    hi = int(np.searchsorted(packed, bounds[1], side="right"))
    return packed[lo:hi]


def _reaching_box(spheres: Sequence[Sphere], keys: np.ndarray, tile_m: float) -> list[Sphere]:
    """The spheres that meet the box of the tiles ``keys`` (with the sphere's tile of
    slack): the others reach none of them."""
    if not spheres:
        return []
    lo = keys.min(axis=0) * tile_m
    origins = np.array([s.origin for s in spheres], np.float64)
    distance = box_distance(lo, (keys.max(axis=0) + 1) * tile_m, origins)
    limit = np.array([s.radius_m for s in spheres], np.float64) + tile_m
    return [s for s, near in zip(spheres, distance <= limit, strict=True) if near]


def _pairs_near(spheres: Sequence[Sphere], keys: np.ndarray, grid: GridSpec) -> int:
    """Pairs of a sphere of ``spheres`` and a tile of ``keys`` it reaches (:func:`tiles_near`
    for each, in blocks of about a million pairs)."""
    if not spheres or len(keys) == 0:
        return 0
    tile_m = grid.tile_size_m
    origins = np.array([s.origin for s in spheres], np.float64)
    limit = np.array([s.radius_m for s in spheres], np.float64) + tile_m  # inf: all
    step = max(1, 2**20 // len(spheres))
    count = 0
    for start in range(0, len(keys), step):
        lo = (keys[start : start + step] * tile_m)[:, None, :]
        count += int(np.count_nonzero(box_distance(lo, lo + tile_m, origins) <= limit))
    return count


def _sorted_isin(values: np.ndarray, among: np.ndarray) -> np.ndarray:
    """Mask of ``values`` found in the sorted array ``among``."""
    if len(among) == 0:
        return np.zeros(len(values), np.bool_)
    at = np.minimum(np.searchsorted(among, values), len(among) - 1)
    return among[at] == values


def _origin(scan: PreparedScan) -> tuple[float, float, float]:
    o = scan.origin_W
    return float(o[0]), float(o[1]), float(o[2])


def plan_remove(
    grid: GridSpec,
    sphere: Sphere,
    existing: np.ndarray,
    owners: Callable[[np.ndarray], Sequence[frozenset[str]]],
    *,
    halo: int = 0,
) -> Plan:
    """Plan the removal of the scan ``sphere.scan_id`` (rule 5) from a volume whose tiles are
    ``existing`` (int64 (n, 3), sorted). The candidates are the tiles the sphere reaches;
    ``owners(keys)`` gives the owners of tiles. In the plan, ``owned`` lists the kept tiles
    the scan owned (their owners change)."""
    scan_id = sphere.scan_id
    existing = np.asarray(existing, np.int64).reshape(-1, 3)
    near = existing[tiles_near(sphere, existing, grid)]
    before = owners(near)
    alone = np.array([not (own - {scan_id}) for own in before], np.bool_).reshape(-1)
    kept = near[~alone]
    owned = np.flatnonzero([scan_id in own for own, a in zip(before, alone, strict=True) if not a])
    steps = [Step(scan_id, np.arange(len(kept), dtype=np.int64), -1)]
    return Plan(grid, kept, np.zeros(len(kept), np.bool_), steps, halo,
                owned={scan_id: owned.astype(np.int64)}, disowned=scan_id,
                deleted=near[alone])  # fmt: skip


def plan_rebuild(
    grid: GridSpec,
    keys: np.ndarray,
    informing: dict[str, np.ndarray],
    *,
    halo: int = 0,
) -> Plan:
    """Plan rebuilding the tiles ``keys`` (int64 (n, 3), sorted) from unknown (rule 6):
    ``informing[scan_id]`` lists the rows of ``keys`` each scan may inform."""
    keys = np.asarray(keys, np.int64).reshape(-1, 3)
    steps = [
        Step(scan_id, np.asarray(rows, np.int64)) for scan_id, rows in sorted(informing.items())
    ]
    return Plan(grid, keys, np.ones(len(keys), np.bool_), steps, halo)
