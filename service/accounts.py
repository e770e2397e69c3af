"""Who may call the service: tokens with a tenant and a role, and idempotency keys.

A token belongs to one tenant and has a role: ``tenant`` (scenes, scans, jobs of that
tenant) or ``admin`` (operators: ``/metrics``, no scenes). Only its SHA-256 hash is stored
(table ``tokens``); the id that ``rangefuse token list`` shows is a prefix of that hash.

An upload sent with an ``Idempotency-Key`` records its response under the tenant and key
(table ``idempotency``), bound to the scene and to the SHA-256 of the upload's parts
(:func:`upload_digest`), so that a retry gets the same answer instead of a second scan, and
the same key with another scan or scene is refused (:class:`IdempotencyKeyReusedError`)
instead of silently answering for the first. Keys are forgotten ``idempotency_ttl_s`` after
they were first used. Both tables live in the store's SQLite file
(:mod:`service._database`); stores written before roles and bound keys existed are migrated
when opened (docs/auth.md).
"""

from __future__ import annotations

import hashlib
import json
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._database import Database

__all__ = [
    "ROLES",
    "Accounts",
    "Caller",
    "IdempotencyKeyReusedError",
    "TokenIdError",
    "TokenRow",
    "hash_token",
    "upload_digest",
]

#: ``tenant``: acts on its tenant's scenes; ``admin``: operators (``/metrics``), no scenes.
ROLES = ("tenant", "admin")
#: Characters of the token hash that ``token list`` shows as the id.
TOKEN_ID_CHARS = 12
#: Fewest characters of an id that ``revoke`` accepts (fewer would revoke by accident).
MIN_TOKEN_ID_CHARS = 6
#: How long a key is kept when the caller gives no other time (``RANGEFUSE_IDEMPOTENCY_TTL_S``).
DEFAULT_IDEMPOTENCY_TTL_S = 24 * 3600.0

_SCHEMA = """
CREATE TABLE IF NOT EXISTS tokens(
    hash TEXT PRIMARY KEY, tenant TEXT NOT NULL, created_at REAL NOT NULL,
    role TEXT NOT NULL DEFAULT 'tenant');
CREATE TABLE IF NOT EXISTS idempotency(
    tenant TEXT NOT NULL, key TEXT NOT NULL, response TEXT NOT NULL,
    scene_id TEXT, body_sha256 TEXT, created_at REAL,
    PRIMARY KEY(tenant, key));
"""

#: Columns added since the first version of each table: (table, column, declaration).
_ADDED_COLUMNS = (
    ("tokens", "role", "TEXT NOT NULL DEFAULT 'tenant'"),
    ("idempotency", "scene_id", "TEXT"),
    ("idempotency", "body_sha256", "TEXT"),
    ("idempotency", "created_at", "REAL"),
)


class IdempotencyKeyReusedError(ValueError):
    """An ``Idempotency-Key`` sent again with another scan or to another scene (422)."""


class TokenIdError(LookupError):
    """A token id that names no token, or more than one."""


@dataclass(frozen=True)
class Caller:
    """Who a valid token speaks for."""

    tenant: str
    role: str


@dataclass(frozen=True)
class TokenRow:
    """A token as ``rangefuse token list`` shows it (never the token itself)."""

    id: str
    tenant: str
    role: str
    created_at: float


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def upload_digest(range_part: bytes, meta_part: bytes) -> str:
    """SHA-256 (hex) of an upload's two parts, each prefixed by its name and length.

    The parts' bytes, not the whole multipart body: the body's boundary is chosen anew by
    most clients for every request, so a faithful retry would not hash the same.
    """
    digest = hashlib.sha256()
    for name, data in ((b"range", range_part), (b"meta", meta_part)):
        digest.update(name + b"\0" + len(data).to_bytes(8, "big"))
        digest.update(data)
    return digest.hexdigest()


class Accounts:
    """Tokens and idempotency keys in the SQLite file at ``path`` (the store's catalog file).

    Parameters
    ----------
    path : Path
        The SQLite file; the tables are created, or migrated from an older layout.
    idempotency_ttl_s : float
        Seconds after its first use that an idempotency key is forgotten (and may be used
        again for another scan).
    """

    def __init__(self, path: Path, idempotency_ttl_s: float = DEFAULT_IDEMPOTENCY_TTL_S) -> None:
        self._db = Database(path, _SCHEMA)
        self.idempotency_ttl_s = float(idempotency_ttl_s)
        self._migrate()

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Accounts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _migrate(self) -> None:
        """Add the columns a store written by an older version lacks (once, in a transaction,
        so that two processes opening the store at once do not both add them)."""
        with self._db.transaction():
            for table, column, declaration in _ADDED_COLUMNS:
                have = {str(row[1]) for row in self._db.rows(f"PRAGMA table_info({table})")}
                if column not in have:
                    self._db.run(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")
            # keys recorded before they had a time expire one TTL after the migration
            self._db.run(
                "UPDATE idempotency SET created_at=? WHERE created_at IS NULL", (time.time(),)
            )
            self._db.run(
                "CREATE INDEX IF NOT EXISTS idempotency_created ON idempotency(created_at)"
            )

    # --- tokens -------------------------------------------------------------------------------
    def create_token(self, tenant: str, role: str = "tenant") -> str:
        """A new bearer token for ``tenant`` with ``role`` (only its hash is stored)."""
        if role not in ROLES:
            raise ValueError(f"role: must be one of {', '.join(ROLES)}, got {role!r}")
        token = secrets.token_urlsafe(32)
        self._db.run(
            "INSERT INTO tokens(hash, tenant, created_at, role) VALUES(?,?,?,?)",
            (hash_token(token), tenant, time.time(), role),
        )
        return token

    def caller(self, token: str) -> Caller | None:
        """The tenant and role of a token, or None for one never made or revoked."""
        rows = self._db.rows("SELECT tenant, role FROM tokens WHERE hash=?", (hash_token(token),))
        return Caller(tenant=str(rows[0][0]), role=str(rows[0][1])) if rows else None

    def tenant(self, token: str) -> str | None:
        """The tenant of a token, or None for a token never made or revoked."""
        found = self.caller(token)
        return found.tenant if found else None

    def n_tokens(self) -> int:
        return int(self._db.rows("SELECT COUNT(*) FROM tokens")[0][0])

    def tokens(self) -> list[TokenRow]:
        """Every token, oldest first, by id (a prefix of its hash)."""
        rows = self._db.rows(
            "SELECT hash, tenant, role, created_at FROM tokens ORDER BY created_at, hash"
        )
        return [
            TokenRow(id=str(h)[:TOKEN_ID_CHARS], tenant=str(t), role=str(r), created_at=float(c))
            for h, t, r, c in rows
        ]

    def revoke_token(self, token_id: str) -> TokenRow:
        """Delete the one token whose hash starts with ``token_id``; it is refused from the
        next request on. Raises :class:`TokenIdError` for an id that is too short, unknown
        or names more than one token."""
        token_id = token_id.strip().lower()
        if len(token_id) < MIN_TOKEN_ID_CHARS or any(c not in "0123456789abcdef" for c in token_id):
            raise TokenIdError(
                f"token id: {token_id!r} is not an id; give at least {MIN_TOKEN_ID_CHARS} "
                "hex characters of an id that `rangefuse token list` shows"
            )
        with self._db.transaction():
            rows = self._db.rows(
                "SELECT hash, tenant, role, created_at FROM tokens WHERE substr(hash, 1, ?)=?",
                (len(token_id), token_id),
            )
            if not rows:
                raise TokenIdError(f"token id: no token {token_id!r} (see `rangefuse token list`)")
            if len(rows) > 1:
                raise TokenIdError(
                    f"token id: {token_id!r} names {len(rows)} tokens; give more characters"
                )
            digest, tenant, role, created_at = rows[0]
            self._db.run("DELETE FROM tokens WHERE hash=?", (digest,))
        return TokenRow(
            id=str(digest)[:TOKEN_ID_CHARS], tenant=str(tenant), role=str(role),
            created_at=float(created_at),
        )  # fmt: skip

    # --- idempotency keys ---------------------------------------------------------------------
    def _forget_expired_keys(self) -> None:
        self._db.run(
            "DELETE FROM idempotency WHERE created_at < ?", (time.time() - self.idempotency_ttl_s,)
        )

    def idempotent_response(self, tenant: str, key: str) -> dict[str, Any] | None:
        """The response recorded for this tenant's key, if any and not expired (whatever
        it was bound to; :meth:`recorded_response` checks the binding)."""
        self._forget_expired_keys()
        rows = self._db.rows(
            "SELECT response FROM idempotency WHERE tenant=? AND key=?", (tenant, key)
        )
        return json.loads(rows[0][0]) if rows else None

    def recorded_response(
        self, tenant: str, key: str, scene_id: str, body_sha256: str
    ) -> dict[str, Any] | None:
        """The response recorded for a retry of this upload, or None for a key not (or no
        longer) in use.

        Raises
        ------
        IdempotencyKeyReusedError
            When the tenant's key was first used for another scene or another body. Keys
            recorded before keys were bound (NULL scene and digest) answer as they did then.
        """
        self._forget_expired_keys()
        rows = self._db.rows(
            "SELECT response, scene_id, body_sha256 FROM idempotency WHERE tenant=? AND key=?",
            (tenant, key),
        )
        if not rows:
            return None
        response, first_scene, first_body = rows[0]
        differs = []
        if first_scene is not None and first_scene != scene_id:
            differs.append(f"it was first used in scene {first_scene!r}, not {scene_id!r}")
        if first_body is not None and first_body != body_sha256:
            differs.append("it was first used for another scan (the range or meta part differs)")
        if differs:
            raise IdempotencyKeyReusedError(
                f"Idempotency-Key: {key!r} is taken: {'; '.join(differs)}; nothing was stored. "
                "A retry must send the same scan to the same scene; a new scan needs a new key"
            )
        return dict(json.loads(response))

    def remember_response(
        self,
        tenant: str,
        key: str,
        response: dict[str, Any],
        scene_id: str | None = None,
        body_sha256: str | None = None,
    ) -> None:
        """Record the response to a key's first use, bound to the scene and the body's
        digest (the first record stays)."""
        self._db.run(
            "INSERT OR IGNORE INTO idempotency(tenant, key, response, scene_id, body_sha256, "
            "created_at) VALUES(?,?,?,?,?,?)",
            (tenant, key, json.dumps(response), scene_id, body_sha256, time.time()),
        )
