"""Who may call the service: tenants and their bearer tokens, and idempotency keys.

A tenant is a name; a token belongs to one tenant and is stored only as its SHA-256 hash
(table ``tokens``). An upload sent with an ``Idempotency-Key`` records its response under
the tenant and key (table ``idempotency``), so that a retry gets the same answer instead of
a second scan. Both tables live in the store's SQLite file (:mod:`service._database`).
"""

from __future__ import annotations

import hashlib
import json
import secrets
import time
from pathlib import Path
from typing import Any

from ._database import Database

__all__ = ["Accounts", "hash_token"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS tokens(
    hash TEXT PRIMARY KEY, tenant TEXT NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS idempotency(
    tenant TEXT NOT NULL, key TEXT NOT NULL, response TEXT NOT NULL,
    PRIMARY KEY(tenant, key));
"""


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class Accounts:
    """Tokens and idempotency keys in the SQLite file at ``path`` (the store's catalog file)."""

    def __init__(self, path: Path) -> None:
        self._db = Database(path, _SCHEMA)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Accounts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- tokens -------------------------------------------------------------------------------
    def create_token(self, tenant: str) -> str:
        """A new bearer token for ``tenant`` (only its hash is stored)."""
        token = secrets.token_urlsafe(32)
        self._db.run(
            "INSERT INTO tokens(hash, tenant, created_at) VALUES(?,?,?)",
            (hash_token(token), tenant, time.time()),
        )
        return token

    def tenant(self, token: str) -> str | None:
        """The tenant of a token, or None for a token that was never made."""
        rows = self._db.rows("SELECT tenant FROM tokens WHERE hash=?", (hash_token(token),))
        return str(rows[0][0]) if rows else None

    def n_tokens(self) -> int:
        return int(self._db.rows("SELECT COUNT(*) FROM tokens")[0][0])

    # --- idempotency keys ---------------------------------------------------------------------
    def idempotent_response(self, tenant: str, key: str) -> dict[str, Any] | None:
        """The response recorded for this tenant's key, if any."""
        rows = self._db.rows(
            "SELECT response FROM idempotency WHERE tenant=? AND key=?", (tenant, key)
        )
        return json.loads(rows[0][0]) if rows else None

    def remember_response(self, tenant: str, key: str, response: dict[str, Any]) -> None:
        self._db.run(
            "INSERT OR IGNORE INTO idempotency(tenant, key, response) VALUES(?,?,?)",
            (tenant, key, json.dumps(response)),
        )
