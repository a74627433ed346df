"""``dancegraph keys create``: make the schema current, then create a tenant's API key."""

from __future__ import annotations

import re

from dancegraph.errors import DanceGraphError
from services import jobs
from services.db import session_scope, upgrade_schema

_TENANT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


def create_key_cli(tenant: str, database_url: str | None = None) -> dict:
    """Create a key for ``tenant``; returns ``{tenant, tenant_id, api_key, prefix}`` (key shown once)."""
    if not _TENANT.match(tenant):
        raise DanceGraphError(
            "tenant names use letters, digits, '.', '_' and '-' (1-100 characters)",
            code="tenant_invalid",
            field="--tenant",
        )
    upgrade_schema(database_url)
    with session_scope(database_url) as session:
        row, key = jobs.create_api_key(session, tenant)
        return {
            "tenant": row.name,
            "tenant_id": row.id,
            "api_key": key,
            "prefix": key[:10],
            "note": "store this key now: only its hash is kept",
        }
