"""The REST service: scenes, scan uploads, background fusion, reconstructions, meshes.

``create_app(settings)`` assembles the FastAPI application from the routers in
``service/api/routes`` (one per resource), the exception handlers and the body-limit
middleware; ``rangefuse serve`` runs it under uvicorn. Requests never run a kernel: uploads
are archived (durably) and queued as jobs whose units of work run on a Dask cluster
(:mod:`service.jobs`).
Every bad input is answered with a 4xx and ``{"detail": "..."}`` naming the problem;
nothing is stored for a refused request.
"""

from __future__ import annotations

import gc
import logging
import sqlite3
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from rangefuse.engine import InvalidInputError
from rangefuse.storage import Store, StoreError

from ._disk import DISK_FULL, is_disk_full
from .accounts import Accounts, IdempotencyKeyReusedError
from .api.deps import Services, ThreadStores
from .api.limits import BodyLimit
from .api.routes import ROUTERS
from .commits import UploadCommitter
from .http_processes import HttpProcesses
from .jobs import JobRunner, JobsElsewhere
from .queue import JobQueue
from .settings import Settings
from .uploads import UploadError

__all__ = ["create_app"]

log = logging.getLogger("rangefuse.service")


# --- one handler per kind of error: status code and {"detail": "..."} ---------------------------


async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    parts = []
    for err in exc.errors():
        where = ".".join(str(x) for x in err.get("loc", ()) if x != "body")
        parts.append(f"{where}: {err.get('msg')}")
    return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)


async def _invalid(request: Request, exc: InvalidInputError) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=422)


async def _upload(request: Request, exc: UploadError) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=400)


async def _store(request: Request, exc: StoreError) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=409)


async def _key_reused(request: Request, exc: IdempotencyKeyReusedError) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=422)


async def _os_error(request: Request, exc: Exception) -> JSONResponse:
    """A full disk is 507 (nothing was stored); any other I/O failure is the service's own
    500, logged with its traceback."""
    if is_disk_full(exc):
        log.warning("%s %s: %s (%s)", request.method, request.url.path, DISK_FULL, exc)
        return JSONResponse({"detail": f"{DISK_FULL} ({exc})"}, status_code=507)
    log.error("%s %s failed", request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": "internal error (logged by the service)"}, status_code=500)


# --- API docs from local copies of Swagger UI and ReDoc (no CDN: they work offline) -----------

_VENDOR = Path(__file__).parent / "static" / "vendor"  # docs/auth.md: versions, licences
_VENDOR_URL = "/static/vendor"


def _add_api_docs(app: FastAPI, openapi_url: str) -> None:
    """``/docs`` (Swagger UI) and ``/redoc`` (ReDoc), their scripts served from
    ``static/vendor`` instead of FastAPI's default CDN (a blank page without internet)."""
    app.mount(_VENDOR_URL, StaticFiles(directory=_VENDOR), name="vendor")
    title = f"{app.title} API"

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=title,
            swagger_js_url=f"{_VENDOR_URL}/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url=f"{_VENDOR_URL}/swagger-ui/swagger-ui.css",
            swagger_favicon_url=f"{_VENDOR_URL}/swagger-ui/favicon-32x32.png",
        )

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=openapi_url,
            title=title,
            redoc_js_url=f"{_VENDOR_URL}/redoc/redoc.standalone.js",
            redoc_favicon_url=f"{_VENDOR_URL}/swagger-ui/favicon-32x32.png",
            with_google_fonts=False,
        )


# --- the application --------------------------------------------------------------------------


def create_app(settings: Settings, primary: bool = True) -> FastAPI:
    """The service over ``settings.data_dir`` (a store, created when missing).

    ``primary``: the process that also runs the jobs and starts the service's other HTTP
    processes (:mod:`service.http_processes`); those are created with ``primary=False``."""
    data_dir = Path(settings.data_dir)
    with Store.open(data_dir, create=True) as store:
        db_path = store.catalog.path  # the service's tables live in the catalog's file
    accounts = Accounts(db_path, settings.idempotency_ttl_s)
    queue = JobQueue(db_path)
    services = Services(
        settings=settings,
        store=ThreadStores(data_dir),
        accounts=accounts,
        queue=queue,
        jobs=JobRunner(data_dir, settings) if primary else JobsElsewhere(queue),
        commits=UploadCommitter(data_dir, accounts),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        others: HttpProcesses | None = None
        if primary:  # before any upload is taken, by this process or the others
            with Store.open(data_dir) as s:  # uploads never acknowledged before a crash
                for row in s.catalog.scenes():
                    s.cleanup_uploads(row.id)
        services.commits.start()
        if primary:
            await run_in_threadpool(services.jobs.start)  # starts (or joins) the Dask cluster
            listening = getattr(app.state, "socket", None)  # set by ``rangefuse serve``
            if listening is not None and settings.http_processes > 1:
                others = HttpProcesses(settings, listening)
                others.start()
        # what start-up made (modules, the app, numba, Dask: some 240,000 objects) is never
        # collected: out of the collector's sight. A full collection under upload load took
        # 0.11 to 0.16 s holding the GIL, every request in flight waiting on it (p99 255-287
        # ms in benchmarks/service_load.py); frozen, none took over 5 ms (p99 167-174 ms)
        gc.freeze()
        yield
        if others is not None:  # they finish their requests and store their uploads
            await run_in_threadpool(others.stop)
        await run_in_threadpool(services.commits.stop)  # stores the uploads in flight
        await run_in_threadpool(services.jobs.stop)

    app = FastAPI(
        title="rangefuse",
        version="0.1.0",
        description="Certainty fusion of registered range scans into 3D models.",
        lifespan=lifespan,
        docs_url=None,  # _add_api_docs: from local copies
        redoc_url=None,
    )
    app.state.services = services
    app.add_exception_handler(RequestValidationError, _validation)  # type: ignore[arg-type]
    app.add_exception_handler(InvalidInputError, _invalid)  # type: ignore[arg-type]
    app.add_exception_handler(UploadError, _upload)  # type: ignore[arg-type]
    app.add_exception_handler(StoreError, _store)  # type: ignore[arg-type]
    app.add_exception_handler(IdempotencyKeyReusedError, _key_reused)  # type: ignore[arg-type]
    app.add_exception_handler(OSError, _os_error)
    app.add_exception_handler(sqlite3.Error, _os_error)
    for router in ROUTERS:
        app.include_router(router)
    _add_api_docs(app, app.openapi_url or "/openapi.json")
    app.mount("/static/app", StaticFiles(directory=_VENDOR.parent / "app"), name="app")  # page
    app.add_middleware(BodyLimit, limit=int(settings.max_upload_mb * 2**20))
    return app
