"""Service configuration (pydantic-settings), one place for every URL, limit and secret.

Environment variables carry the prefix ``DANCEGRAPH_`` (e.g. ``DANCEGRAPH_DATABASE_URL``).
Defaults are the embedded mode: SQLite and a filesystem Celery broker under
``dancegraph.paths.home_dir()``, the object store under ``store_dir()``, the graph store
in-process. Production sets PostgreSQL, Redis and an HTTP graph store through the environment.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from dancegraph.paths import home_dir, store_dir

# Celery queues: analysis+render on one, FBX export (Blender) on its own so each scales apart.
QUEUE_ANALYSIS = "analysis"
QUEUE_FBX = "fbx"


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
        default_factory=_default_store_root, description="object store root folder"
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
    min_audio_seconds: float = Field(
        8.0, gt=0, description="shortest accepted song (two bars at 60 bpm)"
    )
    max_batch_items: int = Field(100, gt=0, description="most songs in one POST /v1/batches")
    job_timeout_s: float = Field(
        600.0, gt=0, description="a running job with no heartbeat this long is stuck"
    )
    job_soft_time_limit_s: float = Field(300.0, gt=0, description="Celery soft time limit per task")
    job_max_attempts: int = Field(3, ge=1, description="tries of a job before it fails for good")
    webhook_secret: str = Field(
        "dancegraph-dev-secret",
        description="HMAC-SHA256 key of webhook signatures (set in production!)",
    )
    webhook_max_attempts: int = Field(5, ge=1)
    webhook_timeout_s: float = Field(10.0, gt=0)
    webhook_backoff_s: float = Field(
        2.0, ge=0, description="first retry delay; doubles each attempt"
    )
    preview_secret: str = Field(
        "dancegraph-dev-preview-secret",
        description="HMAC-SHA256 key of the preview page's ?token= links (set in production!)",
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


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings (cached; tests call ``get_settings.cache_clear()`` after env changes)."""
    return Settings()
