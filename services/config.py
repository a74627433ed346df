"""Service configuration (pydantic-settings), one place for every URL, limit and secret.

Environment variables carry the prefix ``DANCEGRAPH_`` (e.g. ``DANCEGRAPH_DATABASE_URL``).
Defaults are the embedded mode: SQLite and a filesystem Celery broker under
``dancegraph.paths.home_dir()``, the object store under ``store_dir()``, the graph store
in-process. Production sets PostgreSQL, Redis and an HTTP graph store through the environment.
"""

from __future__ import annotations

import math
from collections import Counter
from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from dancegraph.paths import home_dir, store_dir
from dancegraph.store import ObjectStore, open_store

# Celery queues: analysis+render on one, FBX export (Blender) on its own so each scales apart.
QUEUE_ANALYSIS = "analysis"
QUEUE_FBX = "fbx"

# Secrets that ship in public code (the embedded defaults, the old compose fallbacks): a
# deployment that is not the embedded default refuses to start with one of them.
DEFAULT_SECRETS = frozenset(
    {"dancegraph-dev-secret", "dancegraph-dev-preview-secret", "change-me", "change-me-too"}
)
MIN_SECRET_CHARS = 32
MIN_SECRET_DISTINCT = 8  # 32 random hex digits hold 14 different ones on average
MIN_SECRET_BITS = 80.0  # 32 random hex digits: 94 bits or more in 20,000 draws


def secret_weakness(value: str) -> str | None:
    """Why ``value`` is too weak to sign webhooks and preview links, or None when it is not:
    shorter than ``MIN_SECRET_CHARS``, fewer than ``MIN_SECRET_DISTINCT`` different characters
    (40 spaces, 36 × "a"), a repeated unit ("abcdefghij" × 4), or under ``MIN_SECRET_BITS`` by
    its own character frequencies (length × Shannon entropy per character)."""
    if len(value) < MIN_SECRET_CHARS:
        return f"shorter than {MIN_SECRET_CHARS} characters"
    counts = Counter(value)
    if len(counts) < MIN_SECRET_DISTINCT:
        return f"fewer than {MIN_SECRET_DISTINCT} different characters"
    if (value + value).find(value, 1) < len(value):  # a rotation of itself: a repeated unit
        return "a repeated pattern"
    n = len(value)
    if sum(-k * math.log2(k / n) for k in counts.values()) < MIN_SECRET_BITS:
        return f"under {MIN_SECRET_BITS:g} bits by its character frequencies"
    return None


def _default_database_url() -> str:
    return f"sqlite:///{home_dir() / 'dancegraph.db'}"


def _default_broker_folder() -> str:
    return str(home_dir() / "broker")


def _default_store_root() -> str:
    return str(store_dir())


class Settings(BaseSettings):
    """All service settings; read once per process through ``get_settings()``."""

    model_config = SettingsConfigDict(env_prefix="DANCEGRAPH_", extra="ignore")

    database_url: str = Field(
        default_factory=_default_database_url,
        description="SQLAlchemy URL: sqlite:///… (embedded) or postgresql+psycopg://… (production)",
    )
    broker_url: str = Field(
        "filesystem://",
        description="Celery broker: 'filesystem://' (embedded, folders under broker_folder) or redis://…",
    )
    broker_folder: str = Field(
        default_factory=_default_broker_folder,
        description="folder of the filesystem broker (embedded mode only)",
    )
    result_backend: str | None = Field(
        None,
        description="Celery result backend; None: the jobs table is the only record of results",
    )
    store_root: str = Field(
        default_factory=_default_store_root,
        description="filesystem object store root; with an s3:// store_url, the local scratch "
        "and read-cache folder",
    )
    store_url: str = Field(
        "",
        description="'' (the filesystem store at store_root) or s3://bucket/prefix (endpoint and "
        "credentials: AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION)",
    )
    s3_public_endpoint_url: str = Field(
        "",
        description="endpoint that presigned download URLs name, when clients reach the S3 "
        "server under another address than the services do ('' = the same)",
    )
    presigned_url_ttl_s: int = Field(900, gt=0, description="lifetime of a presigned download URL")
    min_free_bytes: int = Field(
        512 * 1024 * 1024,
        ge=0,
        description="/readyz answers not ready when the store's (or scratch) disk has less free",
    )
    db_pool_size: int = Field(10, ge=1, description="PostgreSQL connections kept per process")
    db_max_overflow: int = Field(10, ge=0, description="extra connections under load")
    db_pool_timeout_s: float = Field(
        5.0, gt=0, description="wait for a free connection before answering 503 database_busy"
    )
    graphstore_url: str = Field(
        "local", description="'local' (in-process LocalGraphStore) or the graph store's http(s) URL"
    )
    max_upload_bytes: int = Field(
        256 * 1024 * 1024,
        gt=0,
        description="largest accepted audio upload (a 20-minute CD-quality WAV fits)",
    )
    max_audio_seconds: float = Field(15 * 60.0, gt=0, description="longest accepted song")
    rig_parse_memory_bytes: int = Field(
        2 * 1024**3,
        gt=0,
        description="address-space limit of the sandboxed child that parses a rig file",
    )
    rig_parse_cpu_s: float = Field(
        30.0, gt=0, description="CPU-seconds limit of the sandboxed child that parses a rig file"
    )
    rig_parse_wall_s: float = Field(
        30.0, gt=0, description="wall-clock limit of the sandboxed child that parses a rig file"
    )
    min_audio_seconds: float = Field(
        8.0, gt=0, description="shortest accepted song (two bars at 60 bpm)"
    )
    max_batch_items: int = Field(100, gt=0, description="most songs in one POST /v1/batches")
    library_max_takes: int = Field(200, gt=0, description="most takes in one uploaded library")
    library_max_minutes: float = Field(
        180.0, gt=0, description="most minutes of motion in one uploaded library (all takes)"
    )
    library_max_upload_bytes: int = Field(
        1024 * 1024 * 1024, gt=0, description="largest POST /v1/datasets body (all parts)"
    )
    library_max_per_tenant: int = Field(
        20, gt=0, description="most libraries (names) one tenant may keep"
    )
    library_archive_max_bytes: int = Field(
        4 * 1024 * 1024 * 1024,
        gt=0,
        description="largest total uncompressed size of an uploaded zip/tar",
    )
    library_archive_max_ratio: float = Field(
        200.0, gt=1, description="largest uncompressed/compressed ratio of an archive member"
    )
    library_archive_max_members: int = Field(
        2000, gt=0, description="most members in an uploaded zip/tar"
    )
    library_sandbox_memory_bytes: int = Field(
        6 * 1024 * 1024 * 1024,
        gt=0,
        description="address-space limit of the sandboxed child that parses an upload",
    )
    library_sandbox_cpu_s: float = Field(
        900.0, gt=0, description="CPU-seconds limit of the sandboxed import child"
    )
    library_sandbox_wall_s: float = Field(
        1200.0, gt=0, description="wall-clock limit of the sandboxed import child"
    )
    graphstore_memory_bytes: int = Field(
        2 * 1024 * 1024 * 1024,
        gt=0,
        description="graph-store budget: loaded graphs' arrays above it are evicted, least "
        "recently used first",
    )
    job_timeout_s: float = Field(
        600.0, gt=0, description="a running job with no heartbeat this long is stuck"
    )
    job_soft_time_limit_s: float = Field(300.0, gt=0, description="Celery soft time limit per task")
    job_max_attempts: int = Field(3, ge=1, description="tries of a job before it fails for good")
    webhook_secret: str = Field(
        "dancegraph-dev-secret",
        description="HMAC-SHA256 key of webhook signatures; outside the embedded default a "
        f"private value of at least {MIN_SECRET_CHARS} characters is required",
    )
    webhook_allow_networks: list[str] = Field(
        default_factory=list,
        description="networks (CIDR) a callback_url may point into although they are not public, "
        "e.g. ['127.0.0.1/32'] for a local test receiver; empty: public addresses only",
    )
    webhook_max_attempts: int = Field(5, ge=1)
    webhook_timeout_s: float = Field(10.0, gt=0)
    webhook_backoff_s: float = Field(
        2.0, ge=0, description="first retry delay; doubles each attempt"
    )
    preview_secret: str = Field(
        "dancegraph-dev-preview-secret",
        description="HMAC-SHA256 key of the preview page's ?token= links; outside the embedded "
        f"default a private value of at least {MIN_SECRET_CHARS} characters is required",
    )
    preview_token_ttl_s: int = Field(
        4 * 3600, gt=0, description="lifetime of a preview link handed out with a job"
    )
    public_base_url: str = Field(
        "", description="prefix of absolute URLs in responses ('' = relative)"
    )
    log_json: bool = Field(True, description="structured JSON logs")
    warm_up: bool = Field(
        True,
        description="compile/load the numeric kernels when a worker or graph store starts "
        "(dancegraph.jit), so the first song does not pay ~25 s of compilation",
    )

    @model_validator(mode="after")
    def _refuse_public_secrets(self) -> Settings:
        # A deployment that is not the embedded default (SQLite + filesystem broker) is reachable
        # by others: a secret from public code would let anyone forge webhooks and preview links.
        if self.is_sqlite and self.is_embedded_broker:
            return self
        for name in ("webhook_secret", "preview_secret"):
            value = getattr(self, name)
            weakness = "public" if value in DEFAULT_SECRETS else secret_weakness(value)
            if weakness is not None:
                raise ValueError(
                    f"DANCEGRAPH_{name.upper()} must be set to a private, random value of at "
                    f"least {MIN_SECRET_CHARS} characters outside the embedded default (this "
                    f"one is {weakness}; e.g. openssl rand -hex 32)"
                )
        return self

    @property
    def is_sqlite(self) -> bool:
        return self.database_url.startswith("sqlite")

    @property
    def is_embedded_broker(self) -> bool:
        return self.broker_url.startswith("filesystem://")

    def broker_transport_options(self) -> dict:
        """Celery ``broker_transport_options``: the filesystem transport's folders (created here)."""
        if not self.is_embedded_broker:
            return {"visibility_timeout": int(self.job_timeout_s * 2)}
        root = Path(self.broker_folder)
        out, processed = root / "queue", root / "processed"
        for folder in (out, processed):
            folder.mkdir(parents=True, exist_ok=True)
        return {
            "data_folder_in": str(out),
            "data_folder_out": str(out),
            "processed_folder": str(processed),
            "store_processed": False,
        }


def object_store(settings: Settings) -> ObjectStore:
    """The object store the settings name: S3 (``store_url``) with ``store_root`` as its local
    scratch and cache, or the filesystem store at ``store_root``; one per process and URL."""
    return _object_store(settings.store_url or settings.store_root, settings.store_root)


@lru_cache(maxsize=4)
def _object_store(url: str, scratch: str) -> ObjectStore:
    return open_store(url, scratch)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings (cached; tests call ``get_settings.cache_clear()`` after env changes)."""
    return Settings()
