"""Reconstructions of a scene: ask for one (a job), download the latest mesh."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Header, HTTPException, Query, Response
from fastapi.responses import StreamingResponse
from rangefuse.engine import GridSpec
from rangefuse.engine.meshing import Mesh
from rangefuse.storage.meshes import mesh_bytes

from ...jobs import new_id
from ...queue import JobQueue
from ..deps import CurrentTenant, JobsDep, QueueDep, TenantScene
from ..models import Accepted, ReconstructionIn, problems

__all__ = ["router"]

router = APIRouter(
    prefix="/v1/scenes/{scene_id}",
    tags=["reconstructions"],
    responses=problems(401, 403, 404, 409, 422, 507),
)

_MEDIA = {"ply": "application/octet-stream", "obj": "text/plain", "glb": "model/gltf-binary",
          "stl": "model/stl"}  # fmt: skip


def download_name(name: str, fallback: str) -> str:
    """A file name for a download named after the scene: letters, digits, ``.``, ``-`` and
    ``_`` kept, every other run of characters one ``_``; ``fallback`` (the scene's id) when
    nothing is left."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")[:100]
    return safe or fallback


@router.post("/reconstructions", status_code=202, response_model=Accepted, responses=problems(400))
def reconstruct(
    scene: TenantScene,
    who: CurrentTenant,
    queue: QueueDep,
    jobs: JobsDep,
    body: ReconstructionIn | None = None,
) -> Accepted:
    """Fuse what is pending and mesh the scene (a job); the mesh is then at ``.../mesh``."""
    body = body or ReconstructionIn()
    if body.bounds is not None:  # checked now, not when the job runs
        grid = GridSpec.from_dict(scene.grid)
        GridSpec(grid.voxel_size, grid.tile_size, "mapping", tuple(body.bounds))  # type: ignore[arg-type]
    payload = {"bounds": body.bounds, "refine": body.refine}
    job = queue.create_job(new_id(), who, scene.id, "reconstruct", payload)
    jobs.wake()
    return Accepted.model_validate({"job": {"id": job.id}})


def latest_mesh(queue: JobQueue, scene_id: str, variant: str) -> tuple[str, str, int]:
    """The scene's latest mesh: its file, the ``ETag`` of its ``variant`` (a format, or the
    preview) and its faces; 409 before the first reconstruction."""
    found = queue.mesh(scene_id)
    if found is None:
        raise HTTPException(
            409, "the scene has no reconstruction yet: reconstruct it first "
            "(POST /v1/scenes/{id}/reconstructions)",
        )  # fmt: skip
    path, etag, faces = found
    return path, f'"{etag}-{variant}"', faces


@router.get(
    "/mesh",
    response_class=StreamingResponse,
    responses={
        200: {"content": {m: {} for m in _MEDIA.values()}, "description": "the mesh file"},
        304: {"description": "If-None-Match matched the ETag"},
        **problems(409),
    },
)
def get_mesh(
    scene: TenantScene,
    queue: QueueDep,
    format: Annotated[Literal["ply", "obj", "glb", "stl"], Query()] = "ply",
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The latest reconstruction, streamed, with an ``ETag`` (409 before the first), as a
    file named after the scene (``Content-Disposition``)."""
    path, tag, _ = latest_mesh(queue, scene.id, format)
    if if_none_match == tag:
        return Response(status_code=304, headers={"ETag": tag})
    with np.load(path) as data:
        mesh = Mesh(data["vertices"], data["faces"], data["inferred"], np.zeros((0, 4), np.int64))
    payload = mesh_bytes(mesh, format)

    def chunks() -> Iterator[bytes]:
        for start in range(0, len(payload), 1 << 20):
            yield payload[start : start + (1 << 20)]

    return StreamingResponse(
        chunks(),
        media_type=_MEDIA[format],
        headers={
            "ETag": tag,
            "Content-Length": str(len(payload)),
            "Content-Disposition": (
                f'attachment; filename="{download_name(scene.name, scene.id)}.{format}"'
            ),
        },
    )
