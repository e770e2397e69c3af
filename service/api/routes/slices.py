"""Slices of a scene's fused volume, as PNG images."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Response
from rangefuse.engine import GridSpec
from rangefuse.engine.certainty import decode_logodds
from rangefuse.engine.grid import KEY_LIMIT, unpack_keys
from rangefuse.storage import Store
from rangefuse.storage.importers import encode_png

from ..deps import StoreDep, TenantScene
from ..models import problems

__all__ = ["router"]

router = APIRouter(
    prefix="/v1/scenes/{scene_id}", tags=["slices"], responses=problems(401, 403, 404, 409, 422)
)


@router.get(
    "/slice",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the slice as a PNG"}},
)
def get_slice(
    scene: TenantScene,
    store: StoreDep,
    axis: Annotated[Literal["x", "y", "z"], Query()],
    at: Annotated[float, Query(description="metres")],
) -> Response:
    """The fused certainty on the plane ``axis = at``: free blue, occupied red (darker = more
    certain), unknown grey."""
    if not math.isfinite(at):
        raise HTTPException(422, "at: must be a finite number of metres")
    grid = GridSpec.from_dict(scene.grid)
    reach_m = KEY_LIMIT * grid.tile_size * grid.voxel_size  # where tile keys can lie
    if abs(at) > reach_m:
        raise HTTPException(
            422, f"at: {at:g} m lies beyond the grid's reach of +-{reach_m:g} m from the origin"
        )
    png = _slice_png(store(), scene.id, grid, "xyz".index(axis), at)
    return Response(png, media_type="image/png")


def _slice_png(store: Store, scene_id: str, grid: GridSpec, axis: int, at: float) -> bytes:
    """The fused certainty on a plane: free blue, occupied red (darker = more certain),
    unknown grey; the image covers the tiles that cross the plane."""
    from rangefuse.storage.zarr_tiles import ZarrTiles

    T = grid.tile_size
    h = grid.voxel_size
    index = int(math.floor(at / h))  # the voxel layer whose centre is nearest below
    keys = unpack_keys(store.catalog.tile_keys(scene_id))
    keys = keys[keys[:, axis] == index // T]
    others = [a for a in range(3) if a != axis]
    if len(keys) == 0:
        return encode_png(np.full((1, 1, 3), 128, np.uint8))
    lo = keys[:, others].min(axis=0) * T
    hi = (keys[:, others].max(axis=0) + 1) * T
    if (hi - lo).prod() > 16_000_000:
        raise HTTPException(422, "the slice is too large to render")
    L = np.full(tuple(int(x) for x in hi - lo), np.nan, np.float32)
    tiles = ZarrTiles.open(store.scene_path(scene_id) / "scene.zarr")
    for key, tile in zip(keys, tiles.read(keys), strict=True):
        layer = np.take(tile, index - key[axis] * T, axis=axis)
        a0 = key[others[0]] * T - lo[0]
        b0 = key[others[1]] * T - lo[1]
        L[a0 : a0 + T, b0 : b0 + T] = decode_logodds(layer)
    img = np.full((*L.shape, 3), 128, np.uint8)
    strength = np.clip(np.abs(np.nan_to_num(L)) / 10.0, 0.0, 1.0)
    free = L < 0
    occ = L >= 0
    img[free] = (np.stack([60, 120, 255]) * (0.4 + 0.6 * strength[free, None])).astype(np.uint8)
    img[occ] = (np.stack([230, 40, 40]) * (0.4 + 0.6 * strength[occ, None])).astype(np.uint8)
    return encode_png(np.ascontiguousarray(np.flip(img.transpose(1, 0, 2), axis=0)))
