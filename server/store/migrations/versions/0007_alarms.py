"""Alarms: one row per alarm, its transitions in an append-only table (docs/alarms.md).

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.models import UTCDateTime

revision = "0007"
down_revision = "0006"  # 0006_users (written in parallel as 0006_alarms after 0005)
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "alarms",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("source", sa.String(64), nullable=False),
        sa.Column("code", sa.String(32), nullable=False),
        sa.Column("priority", sa.String(8), nullable=False),
        sa.Column("text", sa.String(400), nullable=False),
        sa.Column("text_key", sa.String(64), nullable=False),
        sa.Column("text_args", sa.Text, nullable=False),
        sa.Column("raised_at", UTCDateTime(), nullable=False),
        sa.Column("cleared_at", UTCDateTime(), nullable=True),
        sa.Column("acked_at", UTCDateTime(), nullable=True),
        sa.Column("acked_by", sa.String(64), nullable=True),
    )
    # one active alarm per (station, source, code): raising it again finds this one
    op.create_index("uq_alarms_active", "alarms", ["station", "source", "code"], unique=True,
                    sqlite_where=sa.text("cleared_at IS NULL"),
                    postgresql_where=sa.text("cleared_at IS NULL"))
    op.create_index("ix_alarms_station_raised", "alarms", ["station", "raised_at"])
    op.create_table(
        "alarm_events",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("alarm_id", sa.BigInteger().with_variant(sa.Integer, "sqlite"),
                  sa.ForeignKey("alarms.id"), nullable=False),
        sa.Column("at", UTCDateTime(), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("by", sa.String(64), nullable=True),
    )
    op.create_index("ix_alarm_events_alarm", "alarm_events", ["alarm_id"])
    # The audit trail's rule, as for measurements and gauge studies: no UPDATE or DELETE.
    if op.get_bind().dialect.name == "sqlite":
        for action in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER alarm_events_no_{action.lower()} BEFORE {action} ON "
                "alarm_events BEGIN SELECT RAISE(ABORT, 'alarm_events is append-only'); END"
            )
    else:
        op.execute(
            "CREATE TRIGGER alarm_events_append_only BEFORE UPDATE OR DELETE ON alarm_events "
            "FOR EACH ROW EXECUTE FUNCTION mvpose_append_only()"
        )
        op.execute(
            "CREATE TRIGGER alarm_events_no_truncate BEFORE TRUNCATE ON alarm_events "
            "FOR EACH STATEMENT EXECUTE FUNCTION mvpose_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS alarm_events_no_update")
        op.execute("DROP TRIGGER IF EXISTS alarm_events_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS alarm_events_append_only ON alarm_events")
        op.execute("DROP TRIGGER IF EXISTS alarm_events_no_truncate ON alarm_events")
    op.drop_table("alarm_events")
    op.drop_table("alarms")
