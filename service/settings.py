"""The service's settings: one pydantic-settings class, ``RANGEFUSE_*`` environment variables."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Where data lives and how the service runs (``RANGEFUSE_DATA_DIR`` and so on)."""

    model_config = SettingsConfigDict(env_prefix="RANGEFUSE_")

    data_dir: Path = Field(default=Path("data"), description="the store: scenes and catalog")
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    max_upload_mb: float = Field(default=256.0, gt=0, description="largest request body")
    workers: int = Field(default=1, ge=1, le=64, description="job worker processes")
    cache_mb: float = Field(default=512.0, gt=0, description="tile cache of each job")
    poll_s: float = Field(default=0.1, gt=0, description="how often the dispatcher looks")
