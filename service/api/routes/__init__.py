"""One ``APIRouter`` per resource (the FastAPI full-stack template's ``api/routes``)."""

from fastapi import APIRouter

from . import health, jobs, reconstructions, scans, scenes, slices, viewer

__all__ = ["ROUTERS"]

#: In the order ``/docs`` lists them.
ROUTERS: tuple[APIRouter, ...] = (
    scenes.router,
    scans.router,
    reconstructions.router,
    slices.router,
    viewer.router,
    jobs.router,
    health.router,
)
