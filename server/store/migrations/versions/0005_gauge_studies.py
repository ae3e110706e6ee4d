"""Gauge studies: one append-only, hash-chained record per study (docs/gauge.md).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.models import UTCDateTime

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "gauge_studies",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("seq", sa.BigInteger, nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("recipe", sa.String(64), nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("created_by", sa.String(64), nullable=False),
        sa.Column("passed", sa.Boolean, nullable=False),
        sa.Column("body", sa.Text, nullable=False),
        sa.Column("prev_hash", sa.String(64), nullable=False),
        sa.Column("hash", sa.String(64), nullable=False, unique=True),
        sa.UniqueConstraint("station", "seq", name="uq_gauge_studies_station_seq"),
    )
    # The audit trail's rule, as for measurements (0001, 0003): no UPDATE, DELETE or TRUNCATE.
    if op.get_bind().dialect.name == "sqlite":
        for action in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER gauge_studies_no_{action.lower()} BEFORE {action} ON "
                "gauge_studies BEGIN SELECT RAISE(ABORT, 'gauge_studies is append-only'); END"
            )
    else:
        op.execute(
            "CREATE TRIGGER gauge_studies_append_only BEFORE UPDATE OR DELETE ON gauge_studies "
            "FOR EACH ROW EXECUTE FUNCTION mvpose_append_only()"
        )
        op.execute(
            "CREATE TRIGGER gauge_studies_no_truncate BEFORE TRUNCATE ON gauge_studies "
            "FOR EACH STATEMENT EXECUTE FUNCTION mvpose_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS gauge_studies_no_update")
        op.execute("DROP TRIGGER IF EXISTS gauge_studies_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS gauge_studies_append_only ON gauge_studies")
        op.execute("DROP TRIGGER IF EXISTS gauge_studies_no_truncate ON gauge_studies")
    op.drop_table("gauge_studies")
