"""Settings from environment variables, in one place, so `pmem --help` can list them all."""

from __future__ import annotations

import gc
import os
from pathlib import Path
from typing import Annotated, Literal
from urllib.parse import urlsplit

import platformdirs
from pydantic import AfterValidator, AliasChoices, BeforeValidator, Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from .types.json_forms import IMAGE_LIMITS


def _database_name(name: str) -> str:
    """A name MongoDB takes for a database (its rules: 1-63 bytes, none of /\\. "$ or NUL)."""
    if not 0 < len(name.encode()) < 64 or set(name) & set('/\\. "$\0'):
        raise ValueError(f"PMEM_DB {name!r} is not a MongoDB database name: 1 to 63 bytes, none of "
                         f"/ \\ . \" $ or a space")
    return name


def _host_names(value: str | None) -> str | None:
    """Host names as a Host header names them, any port: an entry with a port, a scheme or a
    path would never match (every request refused), so it is refused here."""
    for entry in filter(None, (e.strip() for e in (value or "").split(","))):
        if "/" in entry or entry.count(":") == 1 or "]:" in entry:
            raise ValueError(f"{entry!r} is not a host name: give names without a scheme or a "
                             "port (any port is served), e.g. robot.local,10.0.0.5")
    return value


def _origins(value: str) -> str:
    """Origins as browsers send them: scheme://host[:port], nothing after (a trailing / is
    dropped); another form would never match."""
    origins = []
    for entry in filter(None, (e.strip() for e in value.split(","))):
        parts = urlsplit(entry.removesuffix("/"))
        if parts.scheme not in ("http", "https") or not parts.netloc or parts.path or (
                parts.query or parts.fragment):
            raise ValueError(f"{entry!r} is not an origin: scheme://host[:port], e.g. "
                             "https://dashboard.example:8443")
        origins.append(f"{parts.scheme}://{parts.netloc}")
    return ",".join(origins)


def _module_names(value: str) -> str:
    """Python module names, comma-separated (`lab.types,lab.more`)."""
    for name in filter(None, (n.strip() for n in value.split(","))):
        if not all(part.isidentifier() for part in name.split(".")):
            raise ValueError(f"PMEM_TYPES: {name!r} is not a Python module name, e.g. lab.types")
    return value


def _a_folder(value: object) -> object:
    """A folder as given, made absolute (mongod is started elsewhere than where a relative
    one points); empty is unset (it was the current folder: a pid file went to /)."""
    if isinstance(value, str | Path):
        return Path(value).expanduser().absolute() if str(value).strip() else default_data_dir()
    return value


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
    db: Annotated[str, AfterValidator(_database_name)] = Field(
        default="percept_memory", description="PMEM_DB: database name")
    mongo_timeout_ms: int = Field(
        default=5000, ge=1, le=600_000,
        description="PMEM_MONGO_TIMEOUT_MS: how long to wait for an unreachable MongoDB before "
                    "failing (HTTP 503)",
    )
    data_dir: Annotated[Path, BeforeValidator(_a_folder)] = Field(
        default_factory=default_data_dir,
        description="PMEM_DATA_DIR: data directory of the embedded mongod",
    )
    mongod_port: int = Field(
        default=27117, ge=1, le=65535,
        description="PMEM_MONGOD_PORT: loopback port of the embedded mongod",
    )
    mongod_cache_gb: float | None = Field(
        default=None, gt=0, le=4096, allow_inf_nan=False,
        description="PMEM_MONGOD_CACHE_GB: WiredTiger cache size of the embedded mongod; "
        "unset = MongoDB's default, half of (RAM - 1 GB)",
    )
    mongod_oplog_mb: int = Field(
        default=256, ge=32, le=1_048_576,
        description="PMEM_MONGOD_OPLOG_MB: oplog size of the embedded mongod",
    )
    gridfs_threshold: int = Field(
        default=2048, ge=1024, le=2**24,
        description="PMEM_GRIDFS_THRESHOLD: binary values above this many bytes (crops, "
        "images, clouds) leave the documents queries read, for `binaries` (GridFS above "
        "255 kB); smaller ones (feature vectors) stay inline",
    )
    token: str | None = Field(
        default=None, min_length=1,
        description="PMEM_TOKEN: write token for the HTTP API; unset = none on loopback, "
        "a generated one (printed) when serving beyond it",
    )
    allowed_hosts: Annotated[str | None, AfterValidator(_host_names)] = Field(
        default=None,
        description="PMEM_ALLOWED_HOSTS: Host names served, comma-separated, any port; "
        "unset = 127.0.0.1, localhost, ::1 and the --host served on",
    )
    allowed_origins: Annotated[str, AfterValidator(_origins)] = Field(
        default="",
        description="PMEM_ALLOWED_ORIGINS: other origins (scheme://host:port, comma-separated) "
        "whose pages may send POSTs to the API",
    )
    max_request_mb: float = Field(
        default=64, gt=0, le=16_384, allow_inf_nan=False,
        description="PMEM_MAX_REQUEST_MB: largest HTTP request body accepted (413 above)",
    )
    max_image_pixels: int = Field(
        default=IMAGE_LIMITS["max_image_pixels"], ge=1, le=2**31,
        description="PMEM_MAX_IMAGE_PIXELS: largest image accepted, in pixels (checked in the "
                    "PNG/JPEG header before decoding)",
    )
    max_crop_pixels: int = Field(
        default=IMAGE_LIMITS["max_crop_pixels"], ge=1, le=2**31,
        description="PMEM_MAX_CROP_PIXELS: largest cluster crop accepted, in pixels",
    )
    query_timeout_ms: int = Field(
        default=2000, ge=1, le=3_600_000,
        description="PMEM_QUERY_TIMEOUT_MS: server-side time limit of each query operation",
    )
    types: Annotated[str, AfterValidator(_module_names)] = Field(
        default="",
        description="PMEM_TYPES: Python modules of your own annotation types (comma-separated), "
                    "imported by every pmem process, as are those installed packages declare "
                    "under the entry-point group percept_memory.types",
    )

    # --- enrichment workers (ingest/workers.py) ---
    lookup_backend: Literal["simulated", "catalogue", "http"] = Field(
        default="simulated",
        description="PMEM_LOOKUP_BACKEND: what `pmem worker` asks: simulated, catalogue or http",
    )
    lookup_url: str | None = Field(
        default=None, description="PMEM_LOOKUP_URL: the HTTP JSON lookup service (http backend)"
    )
    lookup_auth: str | None = Field(
        default=None,
        description="PMEM_LOOKUP_AUTH: Authorization header sent to it, e.g. 'Bearer <key>'",
    )
    lookup_timeout_s: float = Field(
        default=10.0, gt=0, le=3600, allow_inf_nan=False,
        description="PMEM_LOOKUP_TIMEOUT_S: longest wait for one lookup before it is retried",
    )
    lookup_retries: int = Field(
        default=2, ge=0, le=10,
        description="PMEM_LOOKUP_RETRIES: quick retries of a failed HTTP request in one attempt",
    )
    lookup_concurrency: int = Field(
        default=64, ge=1, le=10_000,
        description="PMEM_LOOKUP_CONCURRENCY: lookups in flight per worker process",
    )
    lookup_cache_radius: int = Field(
        default=10, ge=0, le=32,
        description="PMEM_LOOKUP_CACHE_RADIUS: pHash bits a crop may differ by to reuse a result",
    )
    catalogue_dir: Path | None = Field(
        default=None,
        description="PMEM_CATALOGUE_DIR: product images + products.json (default: the shipped one)",
    )
    simulated_seed: int = Field(
        default=0, description="PMEM_SIMULATED_SEED: seed of the simulated lookup service"
    )
    job_lease_s: float = Field(
        default=30.0, gt=0, le=86_400, allow_inf_nan=False,
        description="PMEM_JOB_LEASE_S: a claimed job is taken over this long after its last "
                    "heartbeat",
    )
    job_max_attempts: int = Field(
        default=5, ge=1, le=1000,
        description="PMEM_JOB_MAX_ATTEMPTS: attempts before a job is marked failed",
    )
    job_backoff_s: float = Field(
        default=2.0, ge=0, le=86_400, allow_inf_nan=False,
        description="PMEM_JOB_BACKOFF_S: wait before the first retry; doubles each attempt",
    )
    consolidator: bool = Field(
        default=True,
        description="PMEM_CONSOLIDATOR: the web app runs the memory pipeline itself (false when "
                    "`pmem consolidate` processes run apart)",
    )
    ingest_processes: int = Field(
        default_factory=lambda: min(os.cpu_count() or 1, 2), ge=1, le=64,
        description="PMEM_INGEST_PROCESSES: processes that parse, validate and encode large "
                    "JSON bodies of scenes for the web app (1: the app's own; default: 2 "
                    "where there are 2 cores; ~140 MB each)",
    )
    map_lease_s: float = Field(
        default=30.0, gt=0, le=86_400, allow_inf_nan=False,
        description="PMEM_MAP_LEASE_S: a map's consolidator is taken over this long after it "
                    "last wrote",
    )
    belief_wait_s: float = Field(
        default=10.0, ge=0, le=300, allow_inf_nan=False,
        description="PMEM_BELIEF_WAIT_S: longest wait of POST /api/scenes?wait=belief",
    )
    similarity_niceness: int = Field(
        default=19, ge=0, le=19,
        description="PMEM_SIMILARITY_NICENESS: CPU niceness of the web app's thread that keeps "
                    "the similarity index current, so that it gives way to ingest",
    )
    similarity_wait_s: float = Field(
        default=1.0, ge=0, le=60, allow_inf_nan=False,
        description="PMEM_SIMILARITY_WAIT_S: longest wait of a similarity search in the web "
                    "app for that thread to catch up (then it searches what is indexed)",
    )


def settings_problems(error: ValidationError) -> str:
    """Bad settings as one line, each named by its environment variable (the start of its
    description), as people set it: `PMEM_MAP_LEASE_S: Input should be ...`."""
    def problem(e: dict) -> str:
        field = Settings.model_fields.get(str(e["loc"][0])) if e["loc"] else None
        name = field.description.split(":")[0] if field and field.description else "settings"
        said = e["msg"].removeprefix("Value error, ")
        return said if said.startswith(name) else f"{name}: {said}"
    return "; ".join(map(problem, error.errors(include_url=False, include_input=False)))


def settings_help() -> str:
    """One line per environment variable, for the CLI's help text."""
    return "\n".join(
        f"  {field.description}" for field in Settings.model_fields.values() if field.description
    )


GC_THRESHOLDS = (50_000, 20, 10)


def collect_less() -> None:
    """Python's cycle collector runs every 700 allocations by default; a scene allocates
    thousands of objects (validating, encoding, deciding who is who), nearly all freed by
    their reference counts. Every pmem process collects every 50,000 instead: 10-20 % less
    CPU per scene stored or consolidated (bench/ingest.py, bench/pipeline.py), for the memory
    of at most that many objects waiting for a collection."""
    gc.set_threshold(*GC_THRESHOLDS)
