"""The service's resource budgets (``docs/budgets.md``): a scene's grid and each uploaded
scan are checked against the limits of the settings before anything is stored.

Refusals are HTTP errors whose message gives the estimate, the limit and the setting that
raises it: 413 for a scene's voxel bytes, 422 otherwise. The estimate is NumPy on a
subsample of the scan (:func:`engine.budget.estimate_scan`, no kernel): a few milliseconds
in the request, in a thread of the pool.

A scene's count is the tiles the catalog holds, plus the estimates of the scans stored but
not fused yet (remembered in this process for the scans it accepted; a scan accepted by
an earlier process counts as much as the one being checked), plus this scan's estimate:
an upper bound, since scans of one scene share tiles.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

from fastapi import HTTPException
from rangefuse.engine import FusionParams, GridSpec, Scan
from rangefuse.engine.budget import (
    LIMITS,
    BudgetError,
    Limits,
    SceneTally,
    check_grid,
    check_scan,
    check_scene,
    estimate_scan,
)
from rangefuse.storage import Store
from rangefuse.storage.catalog import SceneRow

from .settings import Settings

__all__ = ["check_new_scene", "check_upload", "limits_of"]

#: Estimates of the scans accepted lately, per scene (the newest last).
_accepted: dict[str, deque[int]] = {}
_accepted_lock = threading.Lock()
#: Estimates kept per scene: more than a scene's scans ever wait for a job.
_REMEMBERED = 4096


def limits_of(settings: Settings) -> Limits:
    """The limits of the settings, each named by its environment variable in messages."""
    return Limits(
        max_scan_tiles=settings.max_scan_tiles,
        max_scene_tiles=settings.max_scene_tiles,
        max_scene_bytes=settings.max_scene_bytes,
        knobs={name: f"RANGEFUSE_{name.upper()}" for name in LIMITS},
    )


def _refuse(exc: BudgetError) -> HTTPException:
    return HTTPException(413 if exc.limit == "max_scene_bytes" else 422, str(exc))


def check_new_scene(store: Store, tenant: str, grid: GridSpec, settings: Settings) -> None:
    """422 when the tenant has as many scenes as it may, or a closed grid is over budget."""
    have = len(store.catalog.scenes(tenant=tenant))
    if have >= settings.max_scenes_per_tenant:
        raise HTTPException(
            422,
            f"scenes: tenant {tenant!r} has {have} scenes, the limit of "
            f"{settings.max_scenes_per_tenant} per tenant (RANGEFUSE_MAX_SCENES_PER_TENANT); "
            "delete one first",
        )
    try:
        check_grid(grid, limits_of(settings))
    except BudgetError as exc:
        raise HTTPException(422, str(exc)) from None


def check_upload(
    store: Callable[[], Store], scene: SceneRow, scan: Scan, settings: Settings
) -> None:
    """422 (413 for bytes) when the scan, or the scene with it, is over a limit. ``store``
    opens the calling thread's store (``api.deps.StoreDep``)."""
    grid = GridSpec.from_dict(scene.grid)
    params = FusionParams.from_dict(scene.params)
    limits = limits_of(settings)
    try:
        estimate = estimate_scan(scan, params, grid)
        check_scan("scan", estimate, grid, limits)
        catalog = store().catalog
        pending = catalog.n_scans(scene.id, ("stored",))  # a count: uploads stay O(1)
        with _accepted_lock:
            recent = list(_accepted.get(scene.id, ()))[-pending:] if pending else []
        waiting = sum(recent) + (pending - len(recent)) * estimate.tiles
        tally = SceneTally(grid, catalog.n_tiles(scene.id) + waiting)
        tally.add(estimate)
        check_scene(tally, limits)
    except BudgetError as exc:
        raise _refuse(exc) from None
    with _accepted_lock:
        _accepted.setdefault(scene.id, deque(maxlen=_REMEMBERED)).append(estimate.tiles)
