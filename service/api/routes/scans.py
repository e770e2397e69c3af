"""Scans of a scene: upload (acknowledged once on disk), list, one, exact removal."""

from __future__ import annotations

import asyncio
from pathlib import PurePosixPath, PureWindowsPath
from typing import Annotated, Any

from fastapi import APIRouter, Header, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from python_multipart.multipart import MultipartParser, parse_options_header
from rangefuse.engine import sensor_from_dict
from rangefuse.engine.params import params_of
from rangefuse.storage.catalog import SceneRow
from rangefuse.storage.store import PendingScan, Store
from starlette.requests import ClientDisconnect

from ...accounts import upload_digest
from ...budgets import check_upload
from ...jobs import new_id
from ...settings import Settings
from ...uploads import decode_scan
from ..deps import (
    CommitsDep,
    CurrentTenant,
    JobsDep,
    QueueDep,
    SettingsDep,
    StoreDep,
    StoreOpener,
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
                        "(with meta.depth_scale) or float32 TIFF; the scan is named after "
                        "its filename (without extension) unless meta.name is given",
                    },
                    "meta": {
                        "type": "string",
                        "description": "JSON: pose (4x4 sensor to world), sensor (may be "
                        "left out when the scene has one: given at its creation or taken from "
                        f"its first scan), and optionally name, noise {{{_NOISE}}}, "
                        "depth_scale, accept_far_ranges "
                        "(true: fuse a range map that mostly lies beyond the sensor's max_range "
                        "or looks like millimetres, refused with 422 otherwise)",
                    },
                },
            }
        }
    },
}


#: Most parts a scan upload may have (``range``, ``meta``, and two more that are ignored).
_MAX_PARTS = 4


class _Parts:
    """The parts of a multipart body, kept in memory (the body limit bounds them), fed by
    python-multipart's parser. Starlette's form parser spools each file over 1 MB to a
    temporary file, one thread hop per chunk: most of an upload's time in the event loop."""

    def __init__(self) -> None:
        #: Each part's pieces, joined once at the end (one copy of the data, not one a chunk).
        self.parts: dict[str, list[bytes]] = {}
        #: The ``filename`` of each part that has one.
        self.filenames: dict[str, str] = {}
        self._header = b""
        self._value = b""
        self._headers: dict[bytes, bytes] = {}
        self._current: list[bytes] | None = None

    def callbacks(self) -> dict[str, Any]:
        return {
            "on_part_begin": self._begin,
            "on_header_field": self._field,
            "on_header_value": self._header_value,
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._data,
        }

    def _begin(self) -> None:
        self._headers = {}
        self._current = None

    def _field(self, data: bytes, start: int, end: int) -> None:
        self._header += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._header.lower()] = self._value
        self._header, self._value = b"", b""

    def _headers_finished(self) -> None:
        if len(self.parts) >= _MAX_PARTS:
            raise HTTPException(400, f"body: more than {_MAX_PARTS} parts")
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = options.get(b"name", b"").decode("utf-8", "replace")
        if options.get(b"filename"):
            self.filenames[name] = options[b"filename"].decode("utf-8", "replace")
        self._current = self.parts.setdefault(name, [])

    def _data(self, data: bytes, start: int, end: int) -> None:
        if self._current is not None:
            self._current.append(data if start == 0 and end == len(data) else data[start:end])


async def _read_parts(request: Request, max_upload_mb: float) -> tuple[dict[str, bytes], str]:
    """The ``range`` and ``meta`` parts of a multipart body (400 or 413 otherwise), and the
    range part's file name without folders or extension ('' when it has none)."""
    ctype, options = parse_options_header(request.headers.get("content-type", ""))
    boundary = options.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise HTTPException(400, "body: must be multipart/form-data with parts 'range' and 'meta'")
    found = _Parts()
    try:
        parser = MultipartParser(boundary, found.callbacks())  # type: ignore[arg-type]
        async for chunk in request.stream():
            parser.write(chunk)
        parser.finalize()
    except ClientDisconnect:
        raise HTTPException(400, "body: the client stopped before sending it all") from None
    except BodyTooLargeError:
        raise HTTPException(
            413, f"request body is over the limit of {max_upload_mb:g} MB"
        ) from None
    except HTTPException:
        raise
    except Exception as exc:  # malformed multipart (the parser's own errors)
        raise HTTPException(400, f"body: malformed multipart ({exc})") from None
    parts: dict[str, bytes] = {}
    for field in ("range", "meta"):
        if field not in found.parts:
            raise HTTPException(400, f"{field}: missing part")
        parts[field] = b"".join(found.parts.pop(field))
    filename = found.filenames.get("range", "")
    stem = PurePosixPath(PureWindowsPath(filename).name).stem.strip()
    return parts, stem[:200] if stem.isprintable() else ""


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
    parts, filename = await _read_parts(request, settings.max_upload_mb)
    pending, digest = await _staged(
        parts, filename, scene, store, settings, idempotency_key is not None
    )
    future = commits.submit(scene.id, who, idempotency_key, digest, pending)
    response = await asyncio.wrap_future(future)  # stored with the uploads beside it
    jobs.wake()
    return response


async def _staged(
    parts: dict[str, bytes],
    filename: str,
    scene: SceneRow,
    store: StoreOpener,
    settings: Settings,
    with_digest: bool,
) -> tuple[PendingScan, str | None]:
    """:func:`_prepare` in one hop to a thread (all the request's work off the event loop).
    Cancelled (the server stopping under the request), it removes what the thread staged."""
    work = asyncio.ensure_future(
        run_in_threadpool(_prepare, parts, filename, scene, store, settings, with_digest)
    )
    try:
        return await asyncio.shield(work)
    except asyncio.CancelledError:
        work.add_done_callback(_discard_staged)
        raise


def _discard_staged(work: asyncio.Future[tuple[PendingScan, str | None]]) -> None:
    """Remove the scan a cancelled request staged (nothing when staging itself failed)."""
    if not work.cancelled() and work.exception() is None:
        Store.discard_scans([work.result()[0]])


def _prepare(
    parts: dict[str, bytes],
    filename: str,
    scene: SceneRow,
    store: StoreOpener,
    settings: Settings,
    with_digest: bool,
) -> tuple[PendingScan, str | None]:
    """Decode an upload's parts into a scan (named after its file unless ``meta.name`` is
    given), check it against the budgets, stage it in the scene's archive for the group
    commit, and hash the parts when an idempotency key needs it."""
    sensor = None if scene.sensor is None else sensor_from_dict(scene.sensor)
    uploaded = decode_scan(parts["range"], parts["meta"], settings.max_pixels, sensor)
    name = uploaded.name if uploaded.name is not None else (filename or None)
    check_upload(store, scene, uploaded.scan, settings)
    digest = upload_digest(parts["range"], parts["meta"]) if with_digest else None
    return store().stage_scan(scene.id, new_id(), uploaded.scan, name), digest


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
