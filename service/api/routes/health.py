"""The web page, liveness and Prometheus metrics."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from ..deps import CurrentAdmin, JobsDep, QueueDep, StoreDep
from ..models import Health, Problem, problems

__all__ = ["router"]

router = APIRouter(tags=["service"])

_PAGE = (Path(__file__).parents[2] / "static" / "index.html").read_bytes()


@router.get("/", include_in_schema=False)
def index() -> Response:
    """Scenes and jobs with progress, and the latest mesh of a scene (the page asks for
    a token, or takes it from the URL fragment ``#token=``, which browsers never send; it
    keeps it in sessionStorage, and every call it makes carries it)."""
    return Response(_PAGE, media_type="text/html; charset=utf-8")


@router.get("/healthz", response_model=Health, responses={503: {"model": Health}})
def healthz(jobs: JobsDep) -> Health | JSONResponse:
    """Whether jobs can make progress (answers without a token): 503 while no worker of the
    cluster can run units of work."""
    workers = jobs.workers()
    if workers == 0:
        body = Health(status="no worker can run jobs", workers=0)
        return JSONResponse(body.model_dump(), status_code=503)
    return Health(status="ok", workers=workers)


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {"content": {"text/plain": {}}, "description": "Prometheus text format"},
        **problems(401, 422),
        403: {"model": Problem, "description": "a tenant's token (metrics need an admin token)"},
    },
)
def metrics(who: CurrentAdmin, store: StoreDep, queue: QueueDep) -> Response:
    """Scans, tiles and jobs by state, and the voxel updates per second of integration, over
    every tenant: for operators (an admin token; a tenant's token gets 403)."""
    counts = store().catalog.counts()
    jobs = queue.counts()
    lines = ["# TYPE rangefuse_scans gauge"]
    for state in ("stored", "fused", "removing"):
        lines.append(f'rangefuse_scans{{state="{state}"}} {counts["scans"].get(state, 0)}')
    lines += ["# TYPE rangefuse_tiles gauge", f"rangefuse_tiles {counts['tiles']}"]
    lines.append("# TYPE rangefuse_jobs gauge")
    for state in ("queued", "running", "cancelling", "done", "failed", "cancelled"):
        lines.append(f'rangefuse_jobs{{state="{state}"}} {jobs.get(state, 0)}')
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
        f"rangefuse_integration_voxel_updates_per_second {updates / seconds if seconds else 0:.0f}",
    ]
    return Response("\n".join(lines) + "\n", media_type="text/plain; version=0.0.4")
