"""datasets as a tenant resource: owner, import-and-build job state; jobs pin a graph version
(issue 34)

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-06
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")
_TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    with op.batch_alter_table("datasets", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column(
                "tenant_id",
                sa.String(length=36),
                nullable=True,
                comment="owner; NULL: a public library (read-only to tenants)",
            )
        )
        batch_op.add_column(
            sa.Column(
                "graph_name",
                sa.String(length=64),
                nullable=True,
                comment="the graph store's name of this version's graph",
            )
        )
        batch_op.add_column(
            sa.Column("status", sa.String(length=16), nullable=False, server_default="succeeded")
        )
        batch_op.add_column(
            sa.Column("stage", sa.String(length=32), nullable=False, server_default="done")
        )
        batch_op.add_column(
            sa.Column(
                "progress",
                sa.Float(),
                nullable=False,
                server_default="100",
                comment="percent, 0..100",
            )
        )
        batch_op.add_column(
            sa.Column(
                "upload", _JSON, nullable=True, comment="the uploaded files' keys and the manifest"
            )
        )
        batch_op.add_column(
            sa.Column(
                "report", _JSON, nullable=True, comment="per-take results, warnings, graph build"
            )
        )
        batch_op.add_column(sa.Column("error_code", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("error_message", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("error_field", sa.String(length=200), nullable=True))
        batch_op.add_column(sa.Column("attempts", sa.Integer(), nullable=False, server_default="0"))
        batch_op.add_column(sa.Column("crashes", sa.Integer(), nullable=False, server_default="0"))
        batch_op.add_column(sa.Column("worker", sa.String(length=200), nullable=True))
        batch_op.add_column(sa.Column("heartbeat_at", _TS, nullable=True))
        batch_op.add_column(sa.Column("finished_at", _TS, nullable=True))
        batch_op.add_column(
            sa.Column(
                "deleted_at",
                _TS,
                nullable=True,
                comment="deleted by its owner; objects removed once no live job pins it",
            )
        )
        batch_op.add_column(sa.Column("updated_at", _TS, nullable=True))
        batch_op.create_foreign_key(
            "fk_datasets_tenant_id_tenants", "tenants", ["tenant_id"], ["id"], ondelete="CASCADE"
        )
        batch_op.create_index(batch_op.f("ix_datasets_tenant_id"), ["tenant_id"], unique=False)
        batch_op.create_index(
            "ix_datasets_status_heartbeat", ["status", "heartbeat_at"], unique=False
        )
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column(
                "dataset_graph",
                sa.String(length=64),
                nullable=True,
                comment="graph the job pinned when it started",
            )
        )
        batch_op.add_column(
            sa.Column(
                "dataset_version",
                sa.String(length=64),
                nullable=True,
                comment="graph version the job pinned when it started",
            )
        )


def downgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_column("dataset_version")
        batch_op.drop_column("dataset_graph")
    with op.batch_alter_table("datasets", schema=None) as batch_op:
        batch_op.drop_index("ix_datasets_status_heartbeat")
        batch_op.drop_index(batch_op.f("ix_datasets_tenant_id"))
        batch_op.drop_constraint("fk_datasets_tenant_id_tenants", type_="foreignkey")
        for column in (
            "updated_at",
            "deleted_at",
            "finished_at",
            "heartbeat_at",
            "worker",
            "crashes",
            "attempts",
            "error_field",
            "error_message",
            "error_code",
            "report",
            "upload",
            "progress",
            "stage",
            "status",
            "graph_name",
            "tenant_id",
        ):
            batch_op.drop_column(column)
