"""Scenes: create (every default filled in), list, one with its counts, delete."""

from __future__ import annotations

from fastapi import APIRouter, Response
from rangefuse.engine import FusionParams, GridSpec, NoiseModel
from rangefuse.engine.params import default_eps

from ...budgets import check_new_scene
from ...jobs import new_id
from ..deps import CurrentTenant, QueueDep, SettingsDep, StoreDep, TenantScene
from ..models import NoiseIn, SceneDetail, SceneIn, SceneOut, problems

__all__ = ["router"]

router = APIRouter(prefix="/v1/scenes", tags=["scenes"], responses=problems(401, 422))


def _scene_spec(body: SceneIn) -> tuple[GridSpec, FusionParams]:
    """The engine's value objects of a request (they check every value: 422 naming it)."""
    bounds = None if body.bounds is None else tuple(body.bounds)
    grid = GridSpec(body.voxel_size, body.tile_size, body.mode, bounds)  # type: ignore[arg-type]
    noise = body.noise or NoiseIn()
    params = FusionParams(
        noise=NoiseModel(
            eps=noise.eps if noise.eps is not None else default_eps(grid.voxel_size),
            eps_per_m=noise.eps_per_m,
            rho=noise.rho,
            falloff=noise.falloff,
            shape=noise.shape,
        ),
        filter=body.filter,
        max_discontinuity=body.max_discontinuity,
        no_return=body.no_return,
    )
    return grid, params


@router.post("", status_code=201, response_model=SceneOut)
def create_scene(
    body: SceneIn, who: CurrentTenant, store: StoreDep, settings: SettingsDep
) -> SceneOut:
    """A new scene; the answer has every default filled in. 422 past the tenant's scenes or
    for a closed grid over budget (docs/budgets.md)."""
    grid, params = _scene_spec(body)
    check_new_scene(store(), who, grid, settings)
    scene_id = new_id()
    store().create_scene(scene_id, grid, params, name=body.name, tenant=who)
    row = store().catalog.scene(scene_id)
    assert row is not None
    return SceneOut.from_row(row)


@router.get("", response_model=list[SceneOut])
def list_scenes(who: CurrentTenant, store: StoreDep) -> list[SceneOut]:
    """The tenant's scenes, oldest first."""
    return [SceneOut.from_row(r) for r in store().catalog.scenes(tenant=who)]


@router.get("/{scene_id}", response_model=SceneDetail, responses=problems(404))
def get_scene(scene: TenantScene, store: StoreDep) -> SceneDetail:
    """One scene, with the number of its scans and tiles."""
    out = SceneOut.from_row(scene)
    return SceneDetail(
        **out.model_dump(),
        scans=len(store().catalog.scans(scene.id)),
        tiles=store().catalog.n_tiles(scene.id),
    )


@router.delete("/{scene_id}", status_code=204, response_class=Response, responses=problems(404))
def delete_scene(scene: TenantScene, store: StoreDep, queue: QueueDep) -> Response:
    """The scene, its scans, tiles and meshes (waits for a running job of the scene)."""
    store().delete_scene(scene.id)
    queue.forget_scene(scene.id)
    return Response(status_code=204)
