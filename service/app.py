"""The REST service: scenes, scan uploads, background fusion, reconstructions, meshes.

``create_app(settings)`` builds the FastAPI application; ``rangefuse serve`` runs it under
uvicorn. Requests never run a kernel: uploads are archived (durably) and queued as jobs
that worker processes run (:mod:`service.jobs`). Every bad input is answered with a 4xx and
``{"detail": "..."}`` naming the problem; nothing is stored for a refused request.
"""

from __future__ import annotations

import math
import threading
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Depends, FastAPI, Header, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from rangefuse.engine import FusionParams, GridSpec, InvalidInputError, NoiseModel
from rangefuse.engine.certainty import decode_logodds
from rangefuse.engine.defaults import EPS_PER_VOXEL, RHO, TILE_SIZE_VOX
from rangefuse.engine.grid import unpack_keys
from rangefuse.engine.meshing import Mesh
from rangefuse.storage import Store, StoreError
from rangefuse.storage.importers import encode_png
from rangefuse.storage.meshes import mesh_bytes
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .accounts import Accounts
from .jobs import Dispatcher, new_id
from .queue import JobQueue
from .settings import Settings
from .uploads import UploadError, decode_scan

__all__ = ["create_app"]


# --- request bodies ---------------------------------------------------------------------------


class NoiseIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    eps: float | None = Field(default=None, description="noise half-width, metres")
    eps_per_m: float = 0.0
    rho: float = RHO
    falloff: float | None = None
    shape: Literal["linear", "erf"] = "linear"


class SceneIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=200)
    voxel_size: float
    tile_size: int = TILE_SIZE_VOX
    mode: Literal["closed", "mapping"] = "mapping"
    bounds: list[float] | None = None
    noise: NoiseIn | None = None
    filter: Literal["none", "median3", "mean5"] = "none"
    max_discontinuity: float | None = None
    no_return: Literal["free", "invalid"] = "free"


class ReconstructionIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    bounds: list[float] | None = None
    refine: bool = True


# --- a body limit enforced while the body streams in ------------------------------------------


class _TooLargeError(Exception):
    pass


class BodyLimit:
    """ASGI middleware: 413 for a body over ``limit`` bytes, declared or streamed."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await _reject(send, 413, f"request body of {int(declared)} bytes is over the limit "
                                     f"of {self.limit} bytes")  # fmt: skip
            return
        seen = 0
        started = False

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise _TooLargeError
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited, tracking_send)
        except _TooLargeError:
            if not started:
                await _reject(send, 413, f"request body is over the limit of {self.limit} bytes")


async def _reject(send: Send, status: int, detail: str) -> None:
    body = JSONResponse({"detail": detail}).body
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"connection", b"close")],
        }
    )
    await send({"type": "http.response.body", "body": body})


# --- the application --------------------------------------------------------------------------


def _tenant(request: Request, authorization: Annotated[str | None, Header()] = None) -> str:
    """The tenant of the request's bearer token (401 without a valid one)."""
    if not authorization or not authorization.startswith("Bearer "):
        raise HTTPException(401, "missing bearer token (Authorization: Bearer TOKEN)")
    found = request.app.state.accounts.tenant(authorization[7:].strip())
    if found is None:
        raise HTTPException(401, "invalid token")
    return str(found)


Tenant = Annotated[str, Depends(_tenant)]


def create_app(settings: Settings) -> FastAPI:
    """The service over ``settings.data_dir`` (a store, created when missing)."""
    data_dir = Path(settings.data_dir)
    with Store.open(data_dir, create=True) as s:
        db_path = s.catalog.path  # the service's tables live in the catalog's file
    accounts = Accounts(db_path)
    queue = JobQueue(db_path)
    local = threading.local()
    upload_lock = threading.Lock()

    def store() -> Store:
        s = getattr(local, "store", None)
        if s is None:
            s = Store.open(data_dir)
            local.store = s
        return s

    dispatcher = Dispatcher(data_dir, settings.workers, settings.cache_mb, settings.poll_s)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        with Store.open(data_dir) as s:  # uploads never acknowledged before a crash
            for row in s.catalog.scenes():
                s.cleanup_uploads(row.id)
        dispatcher.start()
        yield
        dispatcher.stop()

    app = FastAPI(
        title="rangefuse",
        version="0.1.0",
        description="Certainty fusion of registered range scans into 3D models.",
        lifespan=lifespan,
    )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(x) for x in err.get("loc", ()) if x != "body")
            parts.append(f"{where}: {err.get('msg')}")
        return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)

    @app.exception_handler(InvalidInputError)
    async def _invalid(request: Request, exc: InvalidInputError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    @app.exception_handler(UploadError)
    async def _upload(request: Request, exc: UploadError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=400)

    @app.exception_handler(StoreError)
    async def _store(request: Request, exc: StoreError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=409)

    def scene_row(scene_id: str, who: str) -> Any:
        row = store().catalog.scene(scene_id)
        if row is None or row.tenant != who:
            raise HTTPException(404, f"no scene {scene_id!r}")
        return row

    def scene_out(row: Any) -> dict[str, Any]:
        grid = GridSpec.from_dict(row.grid)
        params = FusionParams.from_dict(row.params)
        n = params.noise
        return {
            "id": row.id,
            "name": row.name,
            "voxel_size": grid.voxel_size,
            "tile_size": grid.tile_size,
            "mode": grid.mode,
            "bounds": None if grid.bounds is None else list(grid.bounds),
            "noise": {
                "eps": n.eps,
                "eps_per_m": n.eps_per_m,
                "rho": n.rho,
                "falloff": n.falloff if n.falloff is not None else n.eps,
                "shape": n.shape,
            },
            "filter": params.filter,
            "max_discontinuity": params.max_discontinuity,
            "no_return": params.no_return,
            "created_at": row.created_at,
        }

    def scan_out(row: Any) -> dict[str, Any]:
        return {"id": row.id, "name": row.name, "state": row.state, "seq": row.seq,
                "checksum": row.checksum, "created_at": row.created_at}  # fmt: skip

    def job_out(job: Any) -> dict[str, Any]:
        return dict(job.to_dict())

    # --- the web page, health and metrics ------------------------------------------------------
    page = (Path(__file__).parent / "static" / "index.html").read_bytes()

    @app.get("/", include_in_schema=False)
    def index() -> Response:
        """Scenes and jobs with progress, and the latest mesh of a scene (the page asks for
        a token, or takes ``?token=``; every call it makes carries it)."""
        return Response(page, media_type="text/html; charset=utf-8")

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/metrics", response_class=Response)
    def metrics(who: Tenant) -> Response:
        counts = store().catalog.counts()
        job_counts = queue.counts()
        lines = ["# TYPE rangefuse_scans gauge"]
        for state in ("stored", "fused", "removing"):
            lines.append(f'rangefuse_scans{{state="{state}"}} {counts["scans"].get(state, 0)}')
        lines += ["# TYPE rangefuse_tiles gauge", f"rangefuse_tiles {counts['tiles']}"]
        lines.append("# TYPE rangefuse_jobs gauge")
        for state in ("queued", "running", "done", "failed"):
            lines.append(f'rangefuse_jobs{{state="{state}"}} {job_counts.get(state, 0)}')
        updates = 0.0
        seconds = 0.0
        for job in queue.jobs(("done",)):
            if job.kind == "integrate" and job.result:
                updates += float(job.result.get("voxel_updates", 0))
                seconds += float(job.result.get("seconds", 0.0))
        lines += [
            "# TYPE rangefuse_integration_voxel_updates_total counter",
            f"rangefuse_integration_voxel_updates_total {updates:.0f}",
            "# TYPE rangefuse_integration_seconds_total counter",
            f"rangefuse_integration_seconds_total {seconds:.3f}",
            "# TYPE rangefuse_integration_voxel_updates_per_second gauge",
            "rangefuse_integration_voxel_updates_per_second "
            f"{updates / seconds if seconds else 0:.0f}",
        ]
        return Response("\n".join(lines) + "\n", media_type="text/plain; version=0.0.4")

    # --- scenes -------------------------------------------------------------------------------
    @app.post("/v1/scenes", status_code=201)
    def create_scene(body: SceneIn, who: Tenant) -> dict[str, Any]:
        if not (math.isfinite(body.voxel_size) and body.voxel_size > 0):
            raise HTTPException(
                422, f"voxel_size: must be a positive number of metres, got {body.voxel_size}"
            )
        bounds = None
        if body.bounds is not None:
            if len(body.bounds) != 6:
                raise HTTPException(422, "bounds: must be six numbers [x0, y0, z0, x1, y1, z1]")
            bounds = tuple(body.bounds)
        grid = GridSpec(body.voxel_size, body.tile_size, body.mode, bounds)  # type: ignore[arg-type]
        noise_in = body.noise or NoiseIn()
        eps = noise_in.eps if noise_in.eps is not None else EPS_PER_VOXEL * body.voxel_size
        noise = NoiseModel(
            eps=eps,
            eps_per_m=noise_in.eps_per_m,
            rho=noise_in.rho,
            falloff=noise_in.falloff,
            shape=noise_in.shape,
        )
        params = FusionParams(
            noise=noise,
            filter=body.filter,
            max_discontinuity=body.max_discontinuity,
            no_return=body.no_return,
        )
        scene_id = new_id()
        store().create_scene(scene_id, grid, params, name=body.name, tenant=who)
        return scene_out(scene_row(scene_id, who))

    @app.get("/v1/scenes")
    def list_scenes(who: Tenant) -> list[dict[str, Any]]:
        return [scene_out(r) for r in store().catalog.scenes(tenant=who)]

    @app.get("/v1/scenes/{scene_id}")
    def get_scene(scene_id: str, who: Tenant) -> dict[str, Any]:
        out = scene_out(scene_row(scene_id, who))
        rows = store().catalog.scans(scene_id)
        out["scans"] = len(rows)
        out["tiles"] = store().catalog.n_tiles(scene_id)
        return out

    @app.delete("/v1/scenes/{scene_id}", status_code=204)
    def delete_scene(scene_id: str, who: Tenant) -> Response:
        scene_row(scene_id, who)
        store().delete_scene(scene_id)
        queue.forget_scene(scene_id)
        return Response(status_code=204)

    # --- scans --------------------------------------------------------------------------------
    @app.post("/v1/scenes/{scene_id}/scans", status_code=202)
    async def upload_scan(
        scene_id: str,
        request: Request,
        who: Tenant,
        idempotency_key: Annotated[str | None, Header()] = None,
    ) -> JSONResponse:
        await run_in_threadpool(scene_row, scene_id, who)
        if idempotency_key is not None and not 0 < len(idempotency_key) <= 200:
            raise HTTPException(400, "Idempotency-Key: must be 1 to 200 characters")
        ctype = request.headers.get("content-type", "")
        if not ctype.startswith("multipart/form-data"):
            raise HTTPException(
                400, "body: must be multipart/form-data with parts 'range' and 'meta'"
            )
        try:
            form = await request.form(max_files=2, max_fields=4)
        except ClientDisconnect:
            raise HTTPException(400, "body: the client stopped before sending it all") from None
        except _TooLargeError:
            raise HTTPException(
                413, f"request body is over the limit of {settings.max_upload_mb:g} MB"
            ) from None
        except Exception as exc:  # malformed multipart (the parser's own errors)
            raise HTTPException(400, f"body: malformed multipart ({exc})") from None
        try:
            parts = {}
            for field in ("range", "meta"):
                item = form.get(field)
                if item is None:
                    raise HTTPException(400, f"{field}: missing part")
                if isinstance(item, str):
                    parts[field] = item.encode()
                else:
                    parts[field] = await item.read()
        finally:
            await form.close()
        uploaded = await run_in_threadpool(decode_scan, parts["range"], parts["meta"])

        def store_it() -> dict[str, Any]:
            with upload_lock:  # idempotency: one retry at a time
                if idempotency_key is not None:
                    seen = accounts.idempotent_response(who, idempotency_key)
                    if seen is not None:
                        return seen
                scan_id = new_id()
                row = store().store_scan(scene_id, scan_id, uploaded.scan, uploaded.name)
                job = queue.queued_job(scene_id, "integrate")
                if job is None:
                    job = queue.create_job(new_id(), who, scene_id, "integrate", {})
                response = {"scan": {"id": row.id, "name": row.name, "state": row.state},
                            "job": {"id": job.id}}  # fmt: skip
                if idempotency_key is not None:
                    accounts.remember_response(who, idempotency_key, response)
                return response

        response = await run_in_threadpool(store_it)
        dispatcher.wake()
        return JSONResponse(response, status_code=202)

    @app.get("/v1/scenes/{scene_id}/scans")
    def list_scans(scene_id: str, who: Tenant) -> list[dict[str, Any]]:
        scene_row(scene_id, who)
        return [scan_out(r) for r in store().catalog.scans(scene_id)]

    @app.get("/v1/scenes/{scene_id}/scans/{scan_id}")
    def get_scan(scene_id: str, scan_id: str, who: Tenant) -> dict[str, Any]:
        scene_row(scene_id, who)
        row = store().catalog.scan(scene_id, scan_id)
        if row is None:
            raise HTTPException(404, f"no scan {scan_id!r} in scene {scene_id!r}")
        return scan_out(row)

    @app.delete("/v1/scenes/{scene_id}/scans/{scan_id}", status_code=202)
    def delete_scan(scene_id: str, scan_id: str, who: Tenant) -> dict[str, Any]:
        scene_row(scene_id, who)
        if store().catalog.scan(scene_id, scan_id) is None:
            raise HTTPException(404, f"no scan {scan_id!r} in scene {scene_id!r}")
        job = queue.create_job(new_id(), who, scene_id, "remove", {"scan_id": scan_id})
        dispatcher.wake()
        return {"job": {"id": job.id}}

    # --- reconstructions, jobs, meshes, slices ------------------------------------------------
    @app.post("/v1/scenes/{scene_id}/reconstructions", status_code=202)
    def reconstruct(
        scene_id: str, who: Tenant, body: ReconstructionIn | None = None
    ) -> dict[str, Any]:
        scene_row(scene_id, who)
        body = body or ReconstructionIn()
        if body.bounds is not None:
            if len(body.bounds) != 6:
                raise HTTPException(422, "bounds: must be six numbers [x0, y0, z0, x1, y1, z1]")
            grid, _ = store().scene_spec(scene_id)
            GridSpec(grid.voxel_size, grid.tile_size, "mapping", tuple(body.bounds))  # type: ignore[arg-type]
        payload = {"bounds": body.bounds, "refine": body.refine}
        job = queue.create_job(new_id(), who, scene_id, "reconstruct", payload)
        dispatcher.wake()
        return {"job": {"id": job.id}}

    @app.get("/v1/jobs")
    def list_jobs(
        who: Tenant, limit: Annotated[int, Query(ge=1, le=1000)] = 50
    ) -> list[dict[str, Any]]:
        """The tenant's most recent jobs, newest first."""
        jobs = queue.jobs(tenant=who)
        return [job_out(j) for j in reversed(jobs[-limit:])]

    @app.get("/v1/jobs/{job_id}")
    def get_job(job_id: str, who: Tenant) -> dict[str, Any]:
        job = queue.job(job_id)
        if job is None or job.tenant != who:
            raise HTTPException(404, f"no job {job_id!r}")
        return job_out(job)

    @app.get("/v1/scenes/{scene_id}/mesh")
    def get_mesh(
        scene_id: str,
        who: Tenant,
        format: Annotated[Literal["ply", "obj", "glb", "stl"], Query()] = "ply",
        if_none_match: Annotated[str | None, Header()] = None,
    ) -> Response:
        scene_row(scene_id, who)
        found = queue.mesh(scene_id)
        if found is None:
            raise HTTPException(409, "no reconstruction yet: POST /v1/scenes/{id}/reconstructions")
        path, etag, _ = found
        tag = f'"{etag}-{format}"'
        if if_none_match == tag:
            return Response(status_code=304, headers={"ETag": tag})
        with np.load(path) as data:
            mesh = Mesh(
                data["vertices"], data["faces"], data["inferred"], np.zeros((0, 4), np.int64)
            )
        payload = mesh_bytes(mesh, format)
        media = {"ply": "application/octet-stream", "obj": "text/plain", "glb": "model/gltf-binary",
                 "stl": "model/stl"}[format]  # fmt: skip

        def chunks() -> Iterator[bytes]:
            for start in range(0, len(payload), 1 << 20):
                yield payload[start : start + (1 << 20)]

        return StreamingResponse(
            chunks(),
            media_type=media,
            headers={
                "ETag": tag,
                "Content-Length": str(len(payload)),
                "Content-Disposition": f'attachment; filename="{scene_id}.{format}"',
            },
        )

    @app.get("/v1/scenes/{scene_id}/slice")
    def get_slice(
        scene_id: str,
        who: Tenant,
        axis: Annotated[Literal["x", "y", "z"], Query()],
        at: Annotated[float, Query(description="metres")],
    ) -> Response:
        scene_row(scene_id, who)
        if not math.isfinite(at):
            raise HTTPException(422, "at: must be a finite number of metres")
        grid, _ = store().scene_spec(scene_id)
        png = _slice_png(store(), scene_id, grid, "xyz".index(axis), at)
        return Response(png, media_type="image/png")

    app.state.store = store
    app.state.accounts = accounts
    app.add_middleware(BodyLimit, limit=int(settings.max_upload_mb * 2**20))
    return app


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
