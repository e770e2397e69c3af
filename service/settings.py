"""The service's settings: one pydantic-settings class, ``RANGEFUSE_*`` environment variables."""

from __future__ import annotations

from pathlib import Path

from dask.utils import parse_bytes
from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict
from rangefuse.engine.budget import LIMITS
from rangefuse.storage.bounded import DEFAULT_MAX_PIXELS

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Where data lives and how the service runs (``RANGEFUSE_DATA_DIR`` and so on)."""

    model_config = SettingsConfigDict(env_prefix="RANGEFUSE_")

    data_dir: Path = Field(default=Path("data"), description="the store: scenes and catalog")
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    max_upload_mb: float = Field(default=256.0, gt=0, description="largest request body")
    max_pixels: int = Field(
        default=DEFAULT_MAX_PIXELS, ge=1,
        description="largest range map an upload may declare (pixels); checked before it is read",
    )  # fmt: skip
    workers: int = Field(
        default=2, ge=1, le=64,
        description="Dask worker processes the service starts (when it joins no scheduler)",
    )  # fmt: skip
    worker_memory: str = Field(
        default="auto",
        description="memory limit of each worker it starts, e.g. 2GiB (auto: the machine's "
        "memory divided among them); a worker over it is restarted",
    )
    scheduler: str | None = Field(
        default=None,
        description="tcp://HOST:PORT of a running Dask scheduler to join instead of starting "
        "workers (the store must be on a file system every worker sees)",
    )
    http_processes: int = Field(
        default=1, ge=1, le=64,
        description="processes answering HTTP requests on the service's socket, each with "
        "its own Python interpreter (uploads are CPU-bound in Python: one process tops out "
        "near one core); the first also runs the jobs",
    )  # fmt: skip
    jobs: int = Field(default=2, ge=1, le=64, description="jobs carried out at once")
    cache_mb: float = Field(default=512.0, gt=0, description="tile cache of each job")
    poll_s: float = Field(default=0.1, gt=0, description="how often the job runner looks")
    idempotency_ttl_s: float = Field(
        default=24 * 3600.0, gt=0,
        description="seconds an upload's Idempotency-Key is kept after its first use",
    )  # fmt: skip
    # resource budgets, declared in engine/budget.py (docs/budgets.md)
    max_scan_tiles: int = Field(
        default=LIMITS["max_scan_tiles"].default, ge=1, description=LIMITS["max_scan_tiles"].help
    )
    max_scene_tiles: int = Field(
        default=LIMITS["max_scene_tiles"].default, ge=1, description=LIMITS["max_scene_tiles"].help
    )
    max_scene_bytes: int = Field(
        default=LIMITS["max_scene_bytes"].default, ge=1,
        description=LIMITS["max_scene_bytes"].help + "; a size such as 64GiB",
    )  # fmt: skip
    max_scenes_per_tenant: int = Field(default=100, ge=1, description="scenes a tenant may have")

    @field_validator("max_scene_bytes", mode="before")
    @classmethod
    def _size(cls, value: object) -> object:
        if isinstance(value, str) and not value.strip().isdigit():
            try:
                return parse_bytes(value)
            except (ValueError, TypeError):
                raise ValueError(
                    f"must be a size such as 64GiB or a number of bytes; got {value!r}"
                ) from None
        return value

    @field_validator("worker_memory")
    @classmethod
    def _memory(cls, value: str) -> str:
        if value != "auto":
            try:
                if parse_bytes(value) <= 0:
                    raise ValueError
            except (ValueError, TypeError):
                raise ValueError(
                    f"must be a size such as 2GiB or 512MB, or auto; got {value!r}"
                ) from None
        return value
