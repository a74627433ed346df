"""SQLAlchemy 2 engine and sessions, built from ``Settings.database_url``.

Works for SQLite (embedded: WAL journal and a busy timeout so the API and worker processes can
share one file) and PostgreSQL (``postgresql+psycopg://``). Engines are cached per URL.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.orm import Session, sessionmaker

from services.config import get_settings

_ENGINES: dict[str, Engine] = {}


def get_engine(url: str | None = None) -> Engine:
    """The engine for ``url`` (default: the settings' database URL), one per URL per process."""
    url = url or get_settings().database_url
    if url not in _ENGINES:
        _ENGINES[url] = _make_engine(url)
    return _ENGINES[url]


def _make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):  # pragma: no cover - trivial
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA busy_timeout=30000")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    settings = get_settings()
    return create_engine(
        url,
        pool_pre_ping=True,
        pool_size=settings.db_pool_size,
        max_overflow=settings.db_max_overflow,
        pool_timeout=settings.db_pool_timeout_s,
        connect_args={
            "connect_timeout": 5
        },  # an unreachable server answers in seconds, not minutes
    )


@lru_cache(maxsize=8)
def _session_factory(url: str) -> sessionmaker[Session]:
    return sessionmaker(bind=get_engine(url), expire_on_commit=False)


def get_sessionmaker(url: str | None = None) -> sessionmaker[Session]:
    return _session_factory(url or get_settings().database_url)


@contextmanager
def session_scope(url: str | None = None) -> Iterator[Session]:
    """A session that commits on success and rolls back on error."""
    session = get_sessionmaker(url)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def create_all(url: str | None = None) -> None:
    """Create the schema directly (embedded mode and tests); production runs ``alembic upgrade head``."""
    from services.models import Base

    Base.metadata.create_all(get_engine(url))


def ping(url: str | None = None) -> None:
    """Raise if the database cannot answer ``SELECT 1``."""
    with get_engine(url).connect() as conn:
        conn.execute(text("SELECT 1"))


def reset_caches() -> None:
    """Dispose of cached engines (tests that switch databases; worker processes after fork)."""
    for engine in _ENGINES.values():
        engine.dispose()
    _ENGINES.clear()
    _session_factory.cache_clear()


def upgrade_schema(url: str | None = None) -> None:
    """Run ``alembic upgrade head`` on ``url`` (default: the settings' database) — idempotent.

    The embedded launcher and ``dancegraph keys create`` call this so SQLite gets the same schema,
    through the same migrations, as PostgreSQL in production.
    """
    from alembic import command
    from alembic.config import Config

    from dancegraph.paths import REPO_ROOT

    cfg = Config(str(REPO_ROOT / "alembic.ini"))
    cfg.set_main_option("script_location", str(REPO_ROOT / "migrations"))
    cfg.attributes["configure_logger"] = False
    url = url or get_settings().database_url
    with get_engine(url).begin() as connection:
        cfg.attributes["connection"] = connection
        command.upgrade(cfg, "head")
