"""Settings from environment variables, in one place, so `pmem --help` can list them all."""

from __future__ import annotations

from pathlib import Path

import platformdirs
from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict


def default_data_dir() -> Path:
    """Where the embedded mongod keeps its files unless PMEM_DATA_DIR says otherwise."""
    return Path(platformdirs.user_data_dir("percept-memory")) / "mongod"


class Settings(BaseSettings):
    """Every knob of percept-memory. Environment variable names are given in `description`."""

    model_config = SettingsConfigDict(env_prefix="PMEM_", extra="ignore")

    mongodb_uri: str | None = Field(
        default=None,
        validation_alias=AliasChoices("MONGODB_URI"),
        description="MONGODB_URI: MongoDB connection string; unset = the embedded local mongod",
    )
    db: str = Field(default="percept_memory", description="PMEM_DB: database name")
    data_dir: Path = Field(
        default_factory=default_data_dir,
        description="PMEM_DATA_DIR: data directory of the embedded mongod",
    )
    mongod_port: int = Field(
        default=27117, ge=1, le=65535,
        description="PMEM_MONGOD_PORT: loopback port of the embedded mongod",
    )
    mongod_cache_gb: float = Field(
        default=0.25, gt=0,
        description="PMEM_MONGOD_CACHE_GB: WiredTiger cache size of the embedded mongod",
    )
    mongod_oplog_mb: int = Field(
        default=256, ge=32,
        description="PMEM_MONGOD_OPLOG_MB: oplog size of the embedded mongod",
    )
    gridfs_threshold: int = Field(
        default=128 * 1024, ge=1024,
        description="PMEM_GRIDFS_THRESHOLD: binary values above this many bytes go to GridFS",
    )
    token: str | None = Field(
        default=None, description="PMEM_TOKEN: write token for the HTTP API"
    )
    max_request_mb: float = Field(
        default=64, gt=0,
        description="PMEM_MAX_REQUEST_MB: largest HTTP request body accepted (413 above)",
    )
    query_timeout_ms: int = Field(
        default=2000, ge=1,
        description="PMEM_QUERY_TIMEOUT_MS: server-side time limit of each query operation",
    )


def settings_help() -> str:
    """One line per environment variable, for the CLI's help text."""
    return "\n".join(
        f"  {field.description}" for field in Settings.model_fields.values() if field.description
    )
