"""``rangefuse serve`` and ``rangefuse token create``: the REST service from the command line."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangefuse.storage import Store

from ._cliutil import CommandError, positive_int

__all__ = ["add_serve_commands"]


def _settings(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from .settings import Settings

    values = {}
    if args.data_dir is not None:
        values["data_dir"] = args.data_dir
    for name in ("host", "port", "workers", "scheduler", "worker_memory"):
        if getattr(args, name, None) is not None:
            values[name] = getattr(args, name)
    try:
        return Settings(**values)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .accounts import Accounts
    from .app import create_app

    settings = _settings(args)
    app = create_app(settings)  # creates the store when missing
    with Store.open(settings.data_dir) as store, Accounts(store.catalog.path) as accounts:
        if accounts.n_tokens() == 0:
            token = accounts.create_token("default")
            print(f"first start: created a token for tenant 'default': {token}", flush=True)
            print("  use it as: Authorization: Bearer TOKEN", flush=True)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")
    return 0


def _cmd_token(args: argparse.Namespace) -> int:
    from .accounts import Accounts

    settings = _settings(args)
    with (
        Store.open(settings.data_dir, create=True) as store,
        Accounts(store.catalog.path) as accounts,
    ):
        print(accounts.create_token(args.tenant))
    return 0


def add_serve_commands(sub: argparse._SubParsersAction) -> None:
    serve = sub.add_parser("serve", help="run the REST service (uvicorn)")
    serve.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    serve.add_argument("--host", default=None, help="address (default 127.0.0.1)")
    serve.add_argument("--port", type=positive_int, default=None, help="port (default 8000)")
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

    token = sub.add_parser("token", help="manage API tokens")
    token_sub = token.add_subparsers(dest="token_command", required=True, metavar="ACTION")
    create = token_sub.add_parser("create", help="create a token for a tenant and print it")
    create.add_argument("--tenant", required=True, help="tenant name")
    create.add_argument("--data-dir", type=Path, default=None, help="store (RANGEFUSE_DATA_DIR)")
    create.set_defaults(func=_cmd_token)
