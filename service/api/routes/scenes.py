"""Scenes: create (every default filled in), list, one with its counts, delete."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, sensor_from_dict
from rangefuse.engine.errors import InvalidSensorError
from rangefuse.engine.params import default_eps
from rangefuse.storage import StoreLockedError

from ...budgets import check_new_scene
from ...jobs import new_id
from ..deps import (
    CurrentTenant,
    JobsDep,
    OwnedScene,
    QueueDep,
    SettingsDep,
    StoreDep,
    TenantScene,
)
from ..models import Accepted, NoiseIn, SceneDetail, SceneIn, SceneOut, problems

__all__ = ["router"]

router = APIRouter(prefix="/v1/scenes", tags=["scenes"], responses=problems(401, 403, 422, 507))


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


def _scene_sensor(body: SceneIn) -> dict[str, Any] | None:
    """The scene's default sensor, checked as an upload's would be (422 naming the field),
    stored in its canonical form."""
    if body.sensor is None:
        return None
    try:
        return sensor_from_dict(body.sensor).to_dict()
    except InvalidSensorError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError, RecursionError) as exc:
        raise InvalidSensorError("sensor", f"not a valid sensor ({exc})") from None


@router.post("", status_code=201, response_model=SceneOut, responses=problems(400))
def create_scene(
    body: SceneIn, who: CurrentTenant, store: StoreDep, settings: SettingsDep
) -> SceneOut:
    """A new scene; the answer has every default filled in. ``sensor`` is optional: uploads
    that give none use it, and without it the first uploaded scan's becomes it. 422 past the
    tenant's scenes or for a closed grid over budget (docs/budgets.md)."""
    grid, params = _scene_spec(body)
    sensor = _scene_sensor(body)
    check_new_scene(store(), who, grid, settings)
    scene_id = new_id()
    store().create_scene(scene_id, grid, params, name=body.name, tenant=who, sensor=sensor)
    row = store().catalog.scene(scene_id)
    assert row is not None
    return SceneOut.from_row(row)


@router.get("", response_model=list[SceneOut])
def list_scenes(who: CurrentTenant, store: StoreDep, queue: QueueDep) -> list[SceneOut]:
    """The tenant's scenes, oldest first (not those being deleted)."""
    going = queue.deleting_scenes()
    return [SceneOut.from_row(r) for r in store().catalog.scenes(tenant=who) if r.id not in going]


@router.get("/{scene_id}", response_model=SceneDetail, responses=problems(404, 409))
def get_scene(scene: TenantScene, store: StoreDep) -> SceneDetail:
    """One scene, with the number of its scans and tiles."""
    out = SceneOut.from_row(scene)
    return SceneDetail(
        **out.model_dump(),
        scans=len(store().catalog.scans(scene.id)),
        tiles=store().catalog.n_tiles(scene.id),
    )


@router.delete(
    "/{scene_id}",
    status_code=204,
    response_class=Response,
    responses={202: {"model": Accepted}, **problems(404)},
)
def delete_scene(
    scene: OwnedScene, who: CurrentTenant, store: StoreDep, queue: QueueDep, jobs: JobsDep
) -> Response:
    """Delete the scene, its scans, tiles and meshes: 204 when done at once; 202 with a
    ``delete`` job when a job of the scene runs (it is cancelled, and the deletion follows
    it). Never waits: while the deletion is pending the scene answers 409, and asking again
    answers the same job."""
    if queue.deletion(scene.id) is None:
        for job in queue.active_jobs(scene.id):
            jobs.cancel(job.id, queue)
        if not queue.active_jobs(scene.id):
            try:
                store().delete_scene(scene.id, wait=False)
            except StoreLockedError:
                pass  # a writer of another process: the job waits for it, not the request
            else:
                queue.forget_scene(scene.id)
                return Response(status_code=204)
    job = queue.delete_job(new_id(), who, scene.id)
    jobs.wake()
    body = Accepted.model_validate({"job": {"id": job.id}})
    return JSONResponse(body.model_dump(), status_code=202)
