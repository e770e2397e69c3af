"""``rangefuse serve`` and ``rangefuse token create|list|revoke``: the REST service from the
command line."""

from __future__ import annotations

import argparse
import copy
import logging
import signal
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._cliutil import CommandError, positive_int

if TYPE_CHECKING:
    from .accounts import Accounts

__all__ = ["serve_arguments", "token_arguments"]


def _settings(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from .settings import Settings

    values = {}
    if args.data_dir is not None:
        values["data_dir"] = args.data_dir
    for name in ("host", "port", "workers", "scheduler", "worker_memory", "http_processes"):
        if getattr(args, name, None) is not None:
            values[name] = getattr(args, name)
    try:
        return Settings(**values)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


class AccessLogWithoutQuery(logging.Filter):
    """Drops the query string from uvicorn's access log lines (``GET /v1/scenes?x=1`` is
    logged as ``GET /v1/scenes``): a query may carry a secret (a token in an old bookmark of
    the page), and a log is read by more people than the service's callers."""

    def filter(self, record: logging.LogRecord) -> bool:
        # uvicorn logs (client_addr, method, path_with_query, http_version, status_code)
        if isinstance(record.args, tuple) and len(record.args) == 5:
            fields = list(record.args)
            if isinstance(fields[2], str):
                fields[2] = fields[2].split("?", 1)[0]
                record.args = tuple(fields)
        return True


def _log_config() -> dict[str, Any]:
    """uvicorn's logging configuration with :class:`AccessLogWithoutQuery` on its access
    logger."""
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config.setdefault("filters", {})["without_query"] = {"()": AccessLogWithoutQuery}
    config["loggers"]["uvicorn.access"]["filters"] = ["without_query"]
    return config


def _kernels_note(scheduler: str | None) -> str:
    """What numba's cache holds: a cold cache means the first jobs compile their kernels."""
    from .warmup import cache_note

    note = cache_note()
    if scheduler:
        note += " (this machine's cache: workers on other machines read their own)"
    return note


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn
    from rangefuse.storage import Store

    from ._malloc import tune_malloc
    from .accounts import Accounts
    from .app import create_app

    settings = _settings(args)
    tune_malloc()
    app = create_app(settings)  # creates the store when missing
    print(f"kernels: {_kernels_note(settings.scheduler)}", flush=True)
    with Store.open(settings.data_dir) as store, Accounts(store.catalog.path) as accounts:
        if accounts.n_tokens() == 0:
            token = accounts.create_token("default")
            admin = accounts.create_token("admin", role="admin")
            print(f"first start: created a token for tenant 'default': {token}", flush=True)
            print(f"first start: admin token (for /metrics; no scenes): {admin}", flush=True)
            print("  use them as: Authorization: Bearer TOKEN", flush=True)
    config = uvicorn.Config(
        app, host=settings.host, port=settings.port, log_level="info", log_config=_log_config()
    )
    # bound here, not by uvicorn: the other HTTP processes answer on the same socket
    app.state.socket = config.bind_socket()
    # A background job of a shell script starts with SIGINT ignored. uvicorn stops on SIGINT
    # all the same, then raises it again for the exit status: ignored, that exit was 0
    # instead of 130 (interrupted). SIGINT stops the service either way; now it says so.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    uvicorn.Server(config).run(sockets=[app.state.socket])
    return 0


def _accounts(args: argparse.Namespace) -> Accounts:
    from rangefuse.storage import Store

    from .accounts import Accounts

    with Store.open(_settings(args).data_dir, create=True) as store:
        return Accounts(store.catalog.path)


def _cmd_token_create(args: argparse.Namespace) -> int:
    tenant = args.tenant.strip()
    if not tenant or len(tenant) > 200 or not tenant.isprintable():
        raise CommandError(f"--tenant: must be 1 to 200 printable characters, got {args.tenant!r}")
    with _accounts(args) as accounts:
        print(accounts.create_token(tenant, role="admin" if args.admin else "tenant"))
    return 0


def _cmd_token_list(args: argparse.Namespace) -> int:
    with _accounts(args) as accounts:
        rows = accounts.tokens()
    width = max([len("tenant"), *(len(r.tenant) for r in rows)])
    print(f"{'id':<12}  {'tenant':<{width}}  {'role':<6}  created (UTC)")
    for r in rows:
        created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r.created_at))
        print(f"{r.id:<12}  {r.tenant:<{width}}  {r.role:<6}  {created}")
    return 0


def _cmd_token_revoke(args: argparse.Namespace) -> int:
    from .accounts import TokenIdError

    with _accounts(args) as accounts:
        try:
            row = accounts.revoke_token(args.id)
        except TokenIdError as exc:
            raise CommandError(str(exc)) from None
    print(f"revoked token {row.id} ({row.role} token of {row.tenant!r})")
    return 0


def serve_arguments(serve: argparse.ArgumentParser) -> None:
    """The arguments of ``serve``."""
    serve.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    serve.add_argument(
        "--host", default=None, help="address to listen on (RANGEFUSE_HOST, default 127.0.0.1)"
    )
    serve.add_argument(
        "--port", type=positive_int, default=None, help="port (RANGEFUSE_PORT, default 8000)"
    )
    serve.add_argument(
        "--http-processes", type=positive_int, default=None, metavar="N",
        help="processes answering requests on the port, each with its own interpreter: more "
        "uploads a second on a machine with cores to spare (RANGEFUSE_HTTP_PROCESSES, default "
        "1)",
    )  # fmt: skip
    serve.add_argument(
        "--workers", type=positive_int, default=None,
        help="Dask worker processes to start for the jobs' units of work (RANGEFUSE_WORKERS, "
        "default 2)",
    )  # fmt: skip
    serve.add_argument(
        "--worker-memory", default=None, metavar="SIZE",
        help="memory limit of each of them, e.g. 2GiB (RANGEFUSE_WORKER_MEMORY, default auto)",
    )  # fmt: skip
    serve.add_argument(
        "--scheduler", default=None, metavar="tcp://HOST:PORT",
        help="join a running Dask cluster instead (RANGEFUSE_SCHEDULER); the store must be on "
        "a file system its workers see",
    )  # fmt: skip
    serve.set_defaults(func=_cmd_serve)


def token_arguments(token: argparse.ArgumentParser) -> None:
    """The actions of ``token``: create, list, revoke."""
    token_sub = token.add_subparsers(dest="token_command", required=True, metavar="ACTION")
    create = token_sub.add_parser("create", help="create a token for a tenant and print it")
    create.add_argument("--tenant", required=True, help="tenant name (for --admin: who uses it)")
    create.add_argument(
        "--admin", action="store_true",
        help="an operator's token: reads /metrics, has no scenes (docs/auth.md)",
    )  # fmt: skip
    create.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    create.set_defaults(func=_cmd_token_create)
    listing = token_sub.add_parser(
        "list", help="list the tokens: id, tenant, role, created (never the tokens themselves)"
    )
    listing.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    listing.set_defaults(func=_cmd_token_list)
    revoke = token_sub.add_parser("revoke", help="revoke a token: refused from the next request")
    revoke.add_argument("id", help="its id as `rangefuse token list` shows it (or a prefix)")
    revoke.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    revoke.set_defaults(func=_cmd_token_revoke)
