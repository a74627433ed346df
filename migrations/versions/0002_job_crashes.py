"""jobs.crashes: crash recoveries counted apart from transient retries

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column(
        "jobs",
        sa.Column(
            "crashes",
            sa.Integer(),
            nullable=False,
            server_default="0",
            comment="times the reaper found the job abandoned by its worker",
        ),
    )


def downgrade() -> None:
    op.drop_column("jobs", "crashes")
