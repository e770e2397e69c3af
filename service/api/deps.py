"""Dependencies of the routes: the service's parts, the caller's tenant, the caller's scene.

Routes declare what they need with the ``Annotated`` aliases below (``StoreDep``,
``CurrentTenant``, ``TenantScene`` ...), as in the FastAPI full-stack template's
``api/deps.py``. :class:`Services` is built once by ``create_app`` and kept in
``app.state``.

A :class:`~storage.Store` holds an SQLite connection that only the thread that opened it
may use, and FastAPI runs each synchronous dependency and route in any thread of its pool;
so ``StoreDep`` is a function that returns *this thread's* store (opened on first use), to
be called where it is used: ``store().catalog.scene(...)``. The accounts and the job queue
open a connection per thread themselves (:mod:`service._database`).

The dependencies are coroutines: FastAPI runs a plain ``def`` dependency in its thread pool,
a hop of a few hundred microseconds of the event loop's time each, and an upload had nine
(most of its time in the loop under load). The token, scene and deletion lookups are one
indexed read each of a WAL database, whose readers never wait on a writer, so they run on
the event loop's thread (which has its own connections, as every thread does).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Request
from rangefuse.storage import Store
from rangefuse.storage.catalog import SceneRow

from ..accounts import Accounts, Caller
from ..commits import UploadCommitter
from ..jobs import Jobs
from ..queue import JobQueue
from ..settings import Settings

__all__ = [
    "AccountsDep",
    "CommitsDep",
    "CurrentAdmin",
    "CurrentTenant",
    "JobsDep",
    "OwnedScene",
    "QueueDep",
    "Services",
    "SettingsDep",
    "StoreDep",
    "TenantScene",
]

StoreOpener = Callable[[], Store]


class ThreadStores:
    """One open :class:`Store` per thread (``__call__`` returns the calling thread's)."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self._local = threading.local()

    def __call__(self) -> Store:
        store = getattr(self._local, "store", None)
        if store is None:
            store = Store.open(self.data_dir)
            self._local.store = store
        return store


@dataclass
class Services:
    """What the routes share: settings, stores, accounts, the job queue and its runner."""

    settings: Settings
    store: ThreadStores
    accounts: Accounts
    queue: JobQueue
    jobs: Jobs
    #: Stores uploads in batches (group commit), checking their idempotency keys.
    commits: UploadCommitter


def _services(request: Request) -> Services:
    services: Services = request.app.state.services
    return services


async def get_settings(request: Request) -> Settings:
    return _services(request).settings


async def get_store(request: Request) -> StoreOpener:
    return _services(request).store


async def get_accounts(request: Request) -> Accounts:
    return _services(request).accounts


async def get_queue(request: Request) -> JobQueue:
    return _services(request).queue


async def get_jobs(request: Request) -> Jobs:
    return _services(request).jobs


async def get_commits(request: Request) -> UploadCommitter:
    return _services(request).commits


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[StoreOpener, Depends(get_store)]
AccountsDep = Annotated[Accounts, Depends(get_accounts)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
JobsDep = Annotated[Jobs, Depends(get_jobs)]
CommitsDep = Annotated[UploadCommitter, Depends(get_commits)]


def _caller(accounts: Accounts, authorization: str | None) -> Caller:
    """Who the request's bearer token speaks for (401 without a valid one)."""
    if not authorization or not authorization.startswith("Bearer "):
        raise HTTPException(401, "missing bearer token (Authorization: Bearer TOKEN)")
    found = accounts.caller(authorization[7:].strip())
    if found is None:
        raise HTTPException(401, "invalid token (unknown or revoked)")
    return found


async def current_tenant(
    accounts: AccountsDep, authorization: Annotated[str | None, Header()] = None
) -> str:
    """The tenant of the request's bearer token (401 without a valid one, 403 for an admin
    token: operators' tokens have no scenes)."""
    caller = _caller(accounts, authorization)
    if caller.role != "tenant":
        raise HTTPException(
            403,
            "admin token: admin tokens read /metrics and have no scenes or jobs; use a tenant "
            "token (rangefuse token create --tenant NAME)",
        )
    return caller.tenant


async def current_admin(
    accounts: AccountsDep, authorization: Annotated[str | None, Header()] = None
) -> str:
    """The name on the request's admin token (401 without a valid token, 403 for a tenant's
    token)."""
    caller = _caller(accounts, authorization)
    if caller.role != "admin":
        raise HTTPException(
            403,
            f"needs an admin token (rangefuse token create --tenant NAME --admin); this is a "
            f"token of tenant {caller.tenant!r}",
        )
    return caller.tenant


CurrentTenant = Annotated[str, Depends(current_tenant)]
CurrentAdmin = Annotated[str, Depends(current_admin)]


async def owned_scene(scene_id: str, who: CurrentTenant, store: StoreDep) -> SceneRow:
    """The scene ``scene_id`` of the path; 404 when it does not exist or is another tenant's
    (the two look the same)."""
    row = store().catalog.scene(scene_id)
    if row is None or row.tenant != who:
        raise HTTPException(404, f"no scene {scene_id!r}")
    return row


OwnedScene = Annotated[SceneRow, Depends(owned_scene)]


async def tenant_scene(scene: OwnedScene, queue: QueueDep) -> SceneRow:
    """The caller's scene, unless it is being deleted (409 naming the deletion's job)."""
    deletion = queue.deletion(scene.id)
    if deletion is not None:
        raise HTTPException(409, f"scene {scene.id!r} is being deleted (job {deletion.id})")
    return scene


TenantScene = Annotated[SceneRow, Depends(tenant_scene)]
