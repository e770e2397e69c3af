"""Jobs: the tenant's latest, and one with its state, progress and result."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query

from ..deps import CurrentTenant, JobsDep, QueueDep
from ..models import JobOut, problems

__all__ = ["router"]

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=problems(401, 403, 422, 507))


@router.get("", response_model=list[JobOut], response_model_exclude_unset=True)
def list_jobs(
    who: CurrentTenant, queue: QueueDep, limit: Annotated[int, Query(ge=1, le=1000)] = 50
) -> list[JobOut]:
    """The tenant's most recent jobs, newest first."""
    jobs = queue.jobs(tenant=who)
    return [JobOut.from_row(j) for j in reversed(jobs[-limit:])]


@router.get(
    "/{job_id}", response_model=JobOut, response_model_exclude_unset=True, responses=problems(404)
)
def get_job(job_id: str, who: CurrentTenant, queue: QueueDep) -> JobOut:
    job = queue.job(job_id)
    if job is None or job.tenant != who:
        raise HTTPException(404, f"no job {job_id!r}")
    return JobOut.from_row(job)


@router.post(
    "/{job_id}/cancel",
    status_code=202,
    response_model=JobOut,
    response_model_exclude_unset=True,
    responses=problems(404, 409),
)
def cancel_job(job_id: str, who: CurrentTenant, queue: QueueDep, jobs: JobsDep) -> JobOut:
    """Cancel a job: a queued one at once (``cancelled``), a running one between two of its
    units of work (``cancelling``, then ``cancelled``; nothing it did is committed)."""
    job = queue.job(job_id)
    if job is None or job.tenant != who:
        raise HTTPException(404, f"no job {job_id!r}")
    if job.state in ("done", "failed", "cancelled"):
        raise HTTPException(409, f"job {job_id!r} already finished: {job.state}")
    if job.kind == "delete":
        raise HTTPException(409, f"job {job_id!r} deletes a scene; a deletion cannot be cancelled")
    cancelled = jobs.cancel(job_id, queue)
    assert cancelled is not None
    return JobOut.from_row(cancelled)
