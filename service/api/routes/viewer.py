"""What the web page's viewer draws: a scene's preview mesh and its scans' placements."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Header, HTTPException, Response
from pydantic import BaseModel, Field
from rangefuse.storage.archive import ArchiveError, ScanArchive

from ...previews import PREVIEW_FACES, preview_of, preview_path
from ..deps import QueueDep, StoreDep, TenantScene
from ..models import problems
from .reconstructions import latest_mesh

__all__ = ["router"]

router = APIRouter(
    prefix="/v1/scenes/{scene_id}", tags=["viewer"], responses=problems(401, 403, 404, 409, 422)
)


class Placement(BaseModel):
    """Where a scan was taken from: the sensor's pose and model (to draw it)."""

    id: str
    name: str | None
    state: str
    pose: list[list[float]] = Field(description="4 x 4, sensor to world")
    sensor: dict[str, Any] = Field(description="the sensor.json form (docs/formats.md)")


@router.get(
    "/preview",
    response_class=Response,
    responses={
        200: {
            "content": {"application/octet-stream": {}},
            "description": "the preview: header, float32 positions, uint32 indices "
            "(docs/webapp.md)",
        },
        304: {"description": "If-None-Match matched the ETag"},
    },
)
def get_preview(
    scene: TenantScene,
    queue: QueueDep,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The latest reconstruction simplified to at most 300,000 faces (made by the
    reconstruction job), measured faces first, then the inferred ones: for viewing; the
    full mesh is at ``.../mesh``. 409 before the first reconstruction."""
    mesh_path, tag, faces = latest_mesh(queue, scene.id, "preview")
    if if_none_match == tag:
        return Response(status_code=304, headers={"ETag": tag})
    cached = preview_path(mesh_path)
    if cached.is_file():
        payload = cached.read_bytes()
    elif faces <= PREVIEW_FACES:  # small enough to send whole: no simplification to run
        with np.load(Path(mesh_path)) as data:  # (nor a coarse level: that is the job's)
            payload = preview_of(
                data["vertices"], data["faces"], data["inferred"], coarse_faces=PREVIEW_FACES
            )
    else:
        raise HTTPException(
            409,
            f"this reconstruction ({faces} faces) has no preview: it was made before previews "
            "existed, or simplifying it failed (see the service's log); reconstruct the scene "
            "again, or download the full mesh",
        )
    return Response(payload, media_type="application/octet-stream", headers={"ETag": tag})


@router.get("/placements", response_model=list[Placement])
def list_placements(scene: TenantScene, store: StoreDep) -> list[Placement]:
    """Every scan's pose and sensor, in order of arrival (the viewer draws pinhole cameras as
    frusta and other sensors at their origins)."""
    s = store()
    archive = ScanArchive(s.scene_path(scene.id) / "scene.zarr")
    out = []
    for row in s.catalog.scans(scene.id):
        try:
            placed = archive.placement(row.id)
        except ArchiveError:  # removed meanwhile, or not yet published
            continue
        out.append(Placement(id=row.id, name=row.name, state=row.state, **placed))
    return out
