"""Scans of a scene: upload (acknowledged once on disk), list, one, exact removal."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Header, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from rangefuse.engine.params import params_of
from starlette.requests import ClientDisconnect

from ...accounts import upload_digest
from ...budgets import check_upload
from ...jobs import new_id
from ...uploads import decode_scan
from ..deps import (
    CommitsDep,
    CurrentTenant,
    JobsDep,
    QueueDep,
    SettingsDep,
    StoreDep,
    TenantScene,
)
from ..limits import BodyTooLargeError
from ..models import Accepted, ScanOut, Upload, problems

__all__ = ["router"]

router = APIRouter(
    prefix="/v1/scenes/{scene_id}/scans",
    tags=["scans"],
    responses=problems(401, 403, 404, 409, 422, 507),
)

_NOISE = ", ".join(p.name for p in params_of("noise"))
_MULTIPART = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["range", "meta"],
                "properties": {
                    "range": {
                        "type": "string",
                        "format": "binary",
                        "description": "the range map: .npy (float), scan .npz, 16-bit PNG "
                        "(with meta.depth_scale) or float32 TIFF",
                    },
                    "meta": {
                        "type": "string",
                        "description": "JSON: pose (4x4 sensor to world), sensor, and "
                        f"optionally name, noise {{{_NOISE}}}, depth_scale, accept_far_ranges "
                        "(true: fuse a range map that mostly lies beyond the sensor's max_range "
                        "or looks like millimetres, refused with 422 otherwise)",
                    },
                },
            }
        }
    },
}


async def _read_parts(request: Request, max_upload_mb: float) -> dict[str, bytes]:
    """The ``range`` and ``meta`` parts of a multipart body (400 or 413 otherwise)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.startswith("multipart/form-data"):
        raise HTTPException(400, "body: must be multipart/form-data with parts 'range' and 'meta'")
    try:
        form = await request.form(max_files=2, max_fields=4)
    except ClientDisconnect:
        raise HTTPException(400, "body: the client stopped before sending it all") from None
    except BodyTooLargeError:
        raise HTTPException(
            413, f"request body is over the limit of {max_upload_mb:g} MB"
        ) from None
    except Exception as exc:  # malformed multipart (the parser's own errors)
        raise HTTPException(400, f"body: malformed multipart ({exc})") from None
    try:
        parts = {}
        for field in ("range", "meta"):
            item = form.get(field)
            if item is None:
                raise HTTPException(400, f"{field}: missing part")
            parts[field] = item.encode() if isinstance(item, str) else await item.read()
    finally:
        await form.close()
    return parts


@router.post(
    "",
    status_code=202,
    response_model=Upload,
    responses=problems(400, 413),
    openapi_extra={"requestBody": _MULTIPART},
)
async def upload_scan(
    scene: TenantScene,
    request: Request,
    who: CurrentTenant,
    store: StoreDep,
    jobs: JobsDep,
    settings: SettingsDep,
    commits: CommitsDep,
    idempotency_key: Annotated[str | None, Header()] = None,
) -> dict[str, Any]:
    """Upload a scan; 202 once it is archived on disk, with the job that fuses it (new
    uploads join the scene's queued ``integrate`` job). With an ``Idempotency-Key``, a retry
    gets the first answer and never stores a second scan; the key is bound to the scene and
    the parts' SHA-256, and reusing it for another scan or scene answers 422."""
    if idempotency_key is not None and not 0 < len(idempotency_key) <= 200:
        raise HTTPException(400, "Idempotency-Key: must be 1 to 200 characters")
    parts = await _read_parts(request, settings.max_upload_mb)
    uploaded = await run_in_threadpool(
        decode_scan, parts["range"], parts["meta"], settings.max_pixels
    )
    await run_in_threadpool(check_upload, store, scene, uploaded.scan, settings)  # budgets
    digest = None
    if idempotency_key is not None:
        digest = await run_in_threadpool(upload_digest, parts["range"], parts["meta"])
    future = commits.submit(scene.id, who, idempotency_key, digest, uploaded)
    response = await asyncio.wrap_future(future)  # stored with the uploads beside it
    jobs.wake()
    return response


@router.get("", response_model=list[ScanOut])
def list_scans(scene: TenantScene, store: StoreDep) -> list[ScanOut]:
    """The scene's scans in order of arrival."""
    return [ScanOut.from_row(r) for r in store().catalog.scans(scene.id)]


@router.get("/{scan_id}", response_model=ScanOut)
def get_scan(scene: TenantScene, scan_id: str, store: StoreDep) -> ScanOut:
    row = store().catalog.scan(scene.id, scan_id)
    if row is None:
        raise HTTPException(404, f"no scan {scan_id!r} in scene {scene.id!r}")
    return ScanOut.from_row(row)


@router.delete("/{scan_id}", status_code=202, response_model=Accepted)
def delete_scan(
    scene: TenantScene,
    scan_id: str,
    who: CurrentTenant,
    store: StoreDep,
    queue: QueueDep,
    jobs: JobsDep,
) -> Accepted:
    """Remove a scan exactly (a job: the volume becomes what it would be without it)."""
    if store().catalog.scan(scene.id, scan_id) is None:
        raise HTTPException(404, f"no scan {scan_id!r} in scene {scene.id!r}")
    job = queue.create_job(new_id(), who, scene.id, "remove", {"scan_id": scan_id})
    jobs.wake()
    return Accepted.model_validate({"job": {"id": job.id}})
